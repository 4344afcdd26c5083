"""Registers the HLM methods with ``lacuna eval`` and the model-file loader.

hlm          the online forward filter (causal, constant time per frame)
hlm-offline  eq. (18) with the smoothed posteriors of the whole recording (not causal)
hlm-lag      the fixed-lag smoother, ``lag`` frames late (default 15; not causal)
"""
from __future__ import annotations

import datetime as _dt
import time
from typing import Any, Sequence

import numpy as np

from hlm import model as _model  # registers the loader
from hlm.model import HLMModel, HLMOptions
from hlm.train import fit
from lacuna.registry import MethodSpec, register_method
from mocap.representation import Representation

# Defaults (section 4 of the paper where it says; representation: see docs/BENCHMARKS.md ## HLM)
DEFAULTS: dict[str, Any] = {
    "styles": 4,
    "cycle_frames": 140,
    "n_states": None,       # M; None = 2 N (section 2)
    "jumps": 3,
    "n_iter": 15,
    "n_var": 3,
    "restarts": 3,
    "seed": 0,
    "root_mode": "raw",
    "normalize": False,
    "eta": 0.1,
    "lam_s": 0.1,
    "zbar_frac": 0.01,
    "adapt_rate": 0.0,
    "lag": 15,
}


def train_model(sequences: Sequence[np.ndarray], channels: Sequence[str], names: Sequence[str] = (),
                progress: bool = False, **options: Any) -> HLMModel:
    """Fit the representation and the HLM on raw sequences [(n_k, n_channels)] -> HLMModel."""
    o = {**DEFAULTS, **{k: v for k, v in options.items() if k in DEFAULTS and v is not None}}
    t0 = time.perf_counter()
    rep = Representation.fit(sequences, channels, root_mode=o["root_mode"], normalize=bool(o["normalize"]))
    feats = [rep.transform(s) for s in sequences]
    res = fit(feats, int(o["styles"]), int(o["cycle_frames"]), n_restarts=int(o["restarts"]), seed=int(o["seed"]),
              n_iter=int(o["n_iter"]), n_var=int(o["n_var"]), progress=progress, n_jumps=int(o["jumps"]),
              lam_s=float(o["lam_s"]), zbar_frac=float(o["zbar_frac"]), eta=float(o["eta"]),
              n_states=o["n_states"])
    secs = time.perf_counter() - t0
    hyper = {k: o[k] for k in ("styles", "cycle_frames", "jumps", "n_iter", "n_var", "restarts", "seed", "eta",
                               "lam_s", "zbar_frac")}
    hyper["n_states"] = int(res.params.n_states)
    meta = {
        "hyperparameters": hyper,
        "training": {
            "data": list(names), "frames": int(sum(s.shape[0] for s in sequences)), "seconds": round(secs, 2),
            "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "bounds": [float(b) for b in res.bounds], "restart_bounds": [float(b) for b in res.restart_bounds],
            "best_seed": res.seed, "psi": res.psi.tolist(),
        },
    }
    return HLMModel(rep, res.params, HLMOptions(adapt_rate=float(o["adapt_rate"]), lag=int(o["lag"])), meta)


def _train(training_set, **options: Any) -> HLMModel:
    return train_model(training_set.sequences, training_set.channels, training_set.names, **options)


def _fill_offline(model: HLMModel, frames: np.ndarray, observed: np.ndarray):
    return model.fill_smoothed(frames, observed)


def _fill_lag(model: HLMModel, frames: np.ndarray, observed: np.ndarray):
    return model.fill_lagged(frames, observed)


register_method(MethodSpec("hlm", _train, "HLM online forward filter (Pan & Torresani 2009)", None, True, dict(DEFAULTS)))
register_method(MethodSpec("hlm-offline", _train, "HLM, eq. (18) with smoothed posteriors (offline)", _fill_offline,
                           False, dict(DEFAULTS)))
register_method(MethodSpec("hlm-lag", _train, "HLM fixed-lag smoother (lag frames late)", _fill_lag, False, dict(DEFAULTS)))
