"""Train ``default``: the Gaussian on the given takes; the stacking weights and std scale either
fitted on held-out takes given for calibration, or the ones shipped in ``blend/weights.json``
(fitted on the VALIDATION split of mocap.splits by bench/default_tune.py)."""
from __future__ import annotations

import datetime as _dt
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from blend.fit import collect, fit_gaussian, fit_weights, velocity_gain, velocity_rms
from blend.groups import groups_or_legacy
from blend.model import GROUP_NAMES, DefaultModel, Settings, Weights

SHIPPED = Path(__file__).with_name("weights.json")
SEEDS = (100, 101, 102)  # occlusion seeds used for calibration (the gaps protocol's are 0-4)


def shipped() -> tuple[Settings, Weights | None, dict[str, Any]]:
    """The settings and weights chosen on VALIDATION (Settings() and None before tuning)."""
    if not SHIPPED.exists():
        return Settings(), None, {}
    d = json.loads(SHIPPED.read_text())
    s = Settings(**{**d["settings"], "knots": tuple(d["settings"]["knots"]), "lags_s": tuple(d["settings"]["lags_s"])})
    w = Weights(*(np.array(d[k], float) for k in ("wv", "wl", "wr", "wg", "sc")))
    if w.wv.shape != (len(GROUP_NAMES), len(s.knots)):
        raise ValueError(f"{SHIPPED}: weights of shape {w.wv.shape} do not match {len(GROUP_NAMES)} groups x {len(s.knots)} knots")
    return s, w, d.get("chosen", {})


def write_shipped(settings: Settings, weights: Weights, chosen: dict[str, Any], path: Path = SHIPPED) -> None:
    d = {"settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in settings.__dict__.items()},
         "wv": weights.wv.round(6).tolist(), "wl": weights.wl.round(6).tolist(), "wr": weights.wr.round(6).tolist(), "wg": weights.wg.round(6).tolist(), "sc": weights.sc.round(6).tolist(),
         "chosen": chosen}
    path.write_text(json.dumps(d, indent=1) + "\n")


def train_model(sequences: Sequence[np.ndarray], channels: Sequence[str], names: Sequence[str] = (),
                calibrate: Sequence[tuple[str, np.ndarray, str]] | None = None, settings: Settings | None = None,
                fps: float | None = None, skeleton: Any = None, **_: Any) -> DefaultModel:
    """``calibrate``: held-out (name, frames, activity) takes to fit the weights on; None = shipped.
    ``skeleton``: the takes' skeleton map (name, .toml file or SkeletonMap; default recognised from
    the bone names): it sets each channel's weight row (blend.groups), recorded in the model."""
    t0 = time.perf_counter()
    s0, w0, chosen = shipped()
    s = settings or s0
    if fps:
        s = Settings(**{**s.__dict__, "fps": float(fps)})
    group, skel = groups_or_legacy(channels, skeleton, names[0] if names else "")
    mean, std, reg, mu, cov = fit_gaussian(sequences, channels, s, group)
    meta = {"training": {"data": list(names), "frames": int(sum(x.shape[0] for x in sequences)),
                         "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")},
            "components": "hold, damped velocity and the conditional Gaussian are all inline in this file",
            "skeleton_map": skel}
    model = DefaultModel(list(channels), mean, std, reg, mu, cov, s, w0 or Weights.initial(len(GROUP_NAMES), len(s.knots)), meta,
                         velocity_rms(sequences, channels), velocity_gain(sequences, channels, s, group=group), group)
    if calibrate:
        w = fit_weights(model, collect(model, calibrate, SEEDS))
        model = model.with_weights(w)
        model.meta["calibration"] = {"data": [n for n, _, _ in calibrate], "seeds": list(SEEDS)}
    else:
        model.meta["calibration"] = {"shipped": str(SHIPPED.name), **chosen} if w0 is not None else {"none": "hold weights"}
    model.meta["training"]["seconds"] = round(time.perf_counter() - t0, 2)
    return model
