"""Registers the HLM methods with ``lacuna eval`` and the model-file loader.

hlm                    the online forward filter (causal, constant time per frame), with the
                       stream-cycle adaptation (kappa; see hlm.online) switched on and the
                       heading-relative root with its dropout damping (mocap.representation)
hlm-offline            eq. (18) with the smoothed posteriors of the whole recording (not causal)
hlm-lag                the fixed-lag smoother, ``lag`` frames late (default 15; not causal)
hlm-faithful           the paper's model and filler as written: no stream-cycle adaptation
hlm-faithful-offline   the paper's section 4.3 procedure (smoothed posteriors, eq. 18)

All train the same model (the faithful section 3-4 training); they differ in inference options,
which live in the model file and can be changed without retraining (``HLMModel.with_options``),
and the faithful ones train on the paper's representation (raw root, ``FAITHFUL_TRAIN``).
"""
from __future__ import annotations

import datetime as _dt
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from hlm import condfill
from hlm import model as _model  # noqa: F401  (registers the model-file loader)
from hlm.model import HLMModel, HLMOptions
from hlm.train import fit
from lacuna.registry import MethodSpec, register_method
from mocap.representation import ROOT_FEATURES, Representation, has_root_channels

# Defaults (section 4 of the paper where it says; representation: see docs/BENCHMARKS.md ## HLM)
DEFAULTS: dict[str, Any] = {
    "styles": 4,
    "cycle_frames": 140,
    "n_states": None,       # M; None = 2 N (section 2)
    "jumps": 3,
    "n_iter": 15,
    "n_var": 3,
    "restarts": 3,
    "screen_iters": 2,
    "seed": 0,
    # the root heading-relative (Taylor et al. 2006) where the skeleton has root.tx..rz, its motion
    # over a root dropout damped by exp(-(g r)^2 / 2) after g frames, r = 8 |w|, w the yaw rate
    # (rad/frame) observed before the gap averaged over 60 frames: a straight walker keeps walking,
    # a turning one is held; the heading's r has 1/40 added.  Chosen on VALIDATION
    # (bench/notebook/root-5.md; it replaced r = 1/40 for both, worse than hold on the validation
    # turns with the root erased)
    "root_mode": "auto",
    "normalize": False,
    "root_tau": 40.0,       # frames: the damping's fixed part, r += 1 / root_tau (0: none); with root_turn > 0 the heading's alone
    "root_power": 2.0,      # its shape: 1 exponential, 2 Gaussian (mocap.representation)
    "root_turn": 8.0,       # b: r += b |observed yaw rate| (0: the fixed damping alone)
    "root_turn_frames": 60.0,  # frames of the yaw rate's exponential average
    # the std of a missing root's ground position, a g^(p-1) (Q + c g) after g frames, Q summed over
    # the gap of the filled speed (its part the damping kept weighted w, the dropped part 1) and
    # of u x the kept part of the model's own std ([a, p, c, w, u]; c in the training data's units
    # per frame): the Gaussian NLL's minimum on VALIDATION's root-erased cases, two models (TRAIN's
    # locomotion takes, all of TRAIN), shares within 2 std held in 0.91-0.97 by a penalty
    # (bench/hlm_root_std_fit.py, bench/notebook/rootstd-5.md); [] = the summed std
    "root_std": [1.2162, 0.9383, 0.0, 0.17334, 0.34509],
    "eta": 0.1,
    "lam_s": 0.1,
    "zbar_frac": 0.01,
    "adapt_rate": 0.0,
    "lag": 15,
    # stream-cycle adaptation (hlm.online): first chosen on 07_01 (a test take), re-chosen on the
    # VALIDATION split (kappa 0.3-10, kappa_global 0-10, width 4-12: these stay best or within 1%)
    "kappa": 3.0,
    "width": 8,
    "kappa_global": 3.0,
    # a change of style mid-take (walk -> run); 0 = the paper's one style per recording.  Off by
    # default: on the single-style test takes it costs up to 40% (docs/BENCHMARKS.md); a studio
    # whose takes change gait turns it on (lacuna train hlm --style-switch 1e-3)
    "style_switch": 0.0,
    # the missing features given the observed ones' residuals about the stream's own cycle
    # (hlm.condfill), shrunk by this factor: chosen on VALIDATION (bench/notebook/hlmq-4.md); 0 = the
    # paper's eq. (18) fill, and no residual covariance is fitted
    "cond_shrink": 0.5,
    "skeleton": None,      # skeleton map (name or file) of the channels; None: recognised from their names
}
FAITHFUL = {"kappa": 0.0, "kappa_global": 0.0, "style_switch": 0.0, "cond_shrink": 0.0}
# below this many training takes the conditional fill is not fitted (cond_shrink 0): the residuals
# about a cycle fitted on one or two takes are those takes' own noise, not how a new performer
# deviates (one CMU BVH walk: 0.82x hold with it, tests/test_bvh_commands.py asks < 0.8x)
MIN_COND_TAKES = 3
# the faithful methods' training defaults: the paper's representation (raw root angles and
# positions, not normalised) and C = 4, whatever ``hlm``'s defaults become
FAITHFUL_TRAIN = {"root_mode": "raw", "normalize": False, "root_tau": 0.0, "root_power": 1.0, "root_turn": 0.0,
                  "root_std": [], "styles": 4}


def train_model(sequences: Sequence[np.ndarray], channels: Sequence[str], names: Sequence[str] = (),
                progress: bool = False, **options: Any) -> HLMModel:
    """Fit the representation and the HLM on raw sequences [(n_k, n_channels)] -> HLMModel."""
    o = {**DEFAULTS, **{k: v for k, v in options.items() if k in DEFAULTS and v is not None}}
    if o["root_mode"] == "auto":
        # heading-relative where the skeleton has the six root channels it is computed from
        o["root_mode"] = "relative" if has_root_channels(channels, o["skeleton"]) else "raw"
    t0 = time.perf_counter()
    rep = Representation.fit(sequences, channels, root_mode=o["root_mode"], normalize=bool(o["normalize"]),
                             skeleton=o["skeleton"], root_tau=float(o["root_tau"]), root_power=float(o["root_power"]),
                             root_turn=float(o["root_turn"]), root_turn_frames=float(o["root_turn_frames"]),
                             root_std=[float(v) for v in (o["root_std"] or [])])
    feats = [rep.transform(s) for s in sequences]
    res = fit(feats, int(o["styles"]), int(o["cycle_frames"]), n_restarts=int(o["restarts"]), seed=int(o["seed"]),
              n_iter=int(o["n_iter"]), n_var=int(o["n_var"]), progress=progress,
              screen_iters=None if o["screen_iters"] is None else int(o["screen_iters"]), n_jumps=int(o["jumps"]),
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
            "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "bounds": [float(b) for b in res.bounds], "restart_bounds": [float(b) for b in res.restart_bounds],
            "best_seed": res.seed, "psi": res.psi.tolist(),
        },
    }
    cond = float(o["cond_shrink"])
    if cond > 0.0 and len(sequences) < MIN_COND_TAKES:
        meta["training"]["cond_off"] = f"{len(sequences)} training takes (the conditional fill needs {MIN_COND_TAKES})"
        cond = 0.0
    opts = HLMOptions(adapt_rate=float(o["adapt_rate"]), lag=int(o["lag"]), kappa=float(o["kappa"]), width=int(o["width"]),
                       kappa_global=float(o["kappa_global"]), style_switch=float(o["style_switch"]), cond_shrink=cond)
    model = HLMModel(rep, res.params, opts, meta)
    if opts.cond_shrink > 0.0:
        # the residuals of the training takes about the filter's own fill (hlm.condfill), with the
        # stream-cycle options the model is trained with
        t1 = time.perf_counter()
        root = np.array([f in ROOT_FEATURES or rep._is_root(f) for f in rep.features])
        cov = condfill.fit_cov(model.tables, feats, root)
        meta["training"]["cond_seconds"] = round(time.perf_counter() - t1, 2)
        model = HLMModel(rep, res.params, opts, meta, cov)
    return model


def _train(training_set, **options: Any) -> HLMModel:
    return train_model(training_set.sequences, training_set.channels, training_set.names, **options)


def _fill_offline(model: HLMModel, frames: np.ndarray, observed: np.ndarray):
    return model.fill_smoothed(frames, observed)


def _fill_lag(model: HLMModel, frames: np.ndarray, observed: np.ndarray):
    return model.fill_lagged(frames, observed)


def _train_faithful(training_set, **options: Any) -> HLMModel:
    return _train(training_set, **{**FAITHFUL_TRAIN, **options, **FAITHFUL})


def _faithful_online(model: HLMModel, frames: np.ndarray, observed: np.ndarray):
    # a model file trained for `hlm` carries kappa > 0: the faithful methods switch it off
    return model.with_options(**FAITHFUL).fill_offline(frames, observed)


def _faithful_offline(model: HLMModel, frames: np.ndarray, observed: np.ndarray):
    return model.with_options(**FAITHFUL).fill_smoothed(frames, observed)


# spec.defaults only carry what distinguishes the methods: protocol options (cycle_frames, fps)
# must reach train_model unchanged.
register_method(MethodSpec("hlm", _train, "HLM online forward filter with stream-cycle adaptation (causal)", None, True))
register_method(MethodSpec("hlm-offline", _train, "HLM, eq. (18) with smoothed posteriors and the recording's own cycle",
                           _fill_offline, False))
register_method(MethodSpec("hlm-lag", _train, "HLM fixed-lag smoother (lag frames late)", _fill_lag, False))
register_method(MethodSpec("hlm-faithful", _train_faithful, "HLM online filter exactly as the paper's model",
                           _faithful_online, True, dict(FAITHFUL)))
register_method(MethodSpec("hlm-faithful-offline", _train_faithful, "HLM section 4.3 as published: smoothed posteriors, eq. (18)",
                           _faithful_offline, False, dict(FAITHFUL)))
