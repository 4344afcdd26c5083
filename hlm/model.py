"""The trained HLM behind the Filler seam: an immutable FeatureModel with a batched online core,
an offline smoother, a fixed-lag stream, and its model file.

Frames in and out are raw channels; ``mocap.representation`` maps them to the features the model
was trained on (``root_mode`` raw or relative, normalised or not, recorded in the file).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hlm import condfill, fast, offline, online
from hlm.params import HLMParams
from hlm.streamcycle import LIVE_STATS
from lacuna import modelfile
from lacuna.filler import BlockFill, Fill, FillerError, FillerState, check_frame
from mocap.feature_model import CoreOut, FeatureModel, FeatureStream
from mocap.representation import Representation

METHOD = "hlm"
_F64, _BOOL = np.dtype(np.float64), np.dtype(np.bool_)


@dataclass
class HLMOptions:
    """Inference options stored with the model (changeable without retraining).

    adapt_rate : forgetting rate per frame of the online transition adaptation (0 = off).
    prior_strength : pseudo-count of the population d in that adaptation.
    n_iter_d : EM steps re-estimating d for a whole recording offline.
    lag : frames of look-ahead of the fixed-lag stream.
    kappa, width : stream-cycle adaptation (prior pseudo-count of each knot of the stream's offset,
        knots 2 width + 1 states apart); kappa = 0 is the paper's filler.  See ``hlm.online``.
    kappa_global : pseudo-count of the stream's constant offset under the knots (0 = none).
    style_switch : probability per frame that the performer changes style (walk -> run) in the
        online filter and the fixed-lag smoother; 0 is the paper's model (one style per recording).
    cond_shrink : the online fill's conditional correction from the observed features' residuals
        (``hlm.condfill``; needs the model's residual covariance); 0 is the paper's fill.
    """

    adapt_rate: float = 0.0
    prior_strength: float = 240.0
    n_iter_d: int = 3
    lag: int = 15
    kappa: float = 0.0
    width: int = 5
    kappa_global: float = 0.0
    style_switch: float = 0.0
    cond_shrink: float = 0.0

    def check(self) -> None:
        if not (0.0 <= self.adapt_rate < 1.0):
            raise ValueError(f"adapt_rate must be in [0, 1) (got {self.adapt_rate})")
        if self.prior_strength <= 0:
            raise ValueError(f"prior_strength must be positive (got {self.prior_strength})")
        if not (0.0 <= self.style_switch < 1.0):
            raise ValueError(f"style_switch must be in [0, 1) (got {self.style_switch})")
        if self.kappa < 0 or self.width < 0 or self.kappa_global < 0:
            raise ValueError(f"kappa, width and kappa_global must be >= 0 "
                             f"(got {self.kappa}, {self.width}, {self.kappa_global})")
        if not (0.0 <= self.cond_shrink <= 1.0):
            raise ValueError(f"cond_shrink must be in [0, 1] (got {self.cond_shrink})")
        if self.n_iter_d < 0 or self.lag < 0:
            raise ValueError(f"n_iter_d and lag must be >= 0 (got {self.n_iter_d}, {self.lag})")


class HLMModel(FeatureModel):
    """A trained Hierarchical Locomotion Model.

    Parameters
    ----------
    representation : the feature space.  params : learned HLM quantities (feature space).
    options : inference options.  meta : hyperparameters, training data names, times, bounds.
    cond_cov : (C, F, F) residual covariances per style of the conditional fill (``hlm.condfill``), or None
        (files written before it, the faithful methods): the online fill is then eq. (18) alone.
    """

    method = METHOD
    causal = True
    core_sparse_keys = ("D", "W", "G", "GW")   # the stream-cycle statistics: touched only at live knots

    def __init__(self, representation: Representation, params: HLMParams, options: HLMOptions | None = None,
                 meta: dict[str, Any] | None = None, cond_cov: np.ndarray | None = None):
        self.representation = representation
        self.params = params
        self.options = options or HLMOptions()
        self.options.check()
        self.meta = dict(meta or {})
        F = representation.n_features
        if params.mu.shape[2] != F:
            raise ValueError(f"HLM parameters have {params.mu.shape[2]} features, representation has {F}")
        self.tables = online.FilterTables.build(params.mu, params.var, params.lam, params.tau, params.d_population(),
                                                self.options.adapt_rate, self.options.prior_strength,
                                                self.options.kappa, self.options.width, self.options.kappa_global,
                                                self.options.style_switch)
        C = params.mu.shape[0]
        if cond_cov is not None and np.shape(cond_cov) != (C, F, F):
            raise ValueError(f"cond_cov must be ({C}, {F}, {F}) (got {np.shape(cond_cov)})")
        self.cond_cov = cond_cov
        # the correction runs only where it was fitted and asked for
        self.cond = (condfill.CondTables(cond_cov, self.options.cond_shrink)
                     if cond_cov is not None and self.options.cond_shrink > 0.0 else None)

    def with_options(self, **kw) -> HLMModel:
        """A copy with other inference options (the learned parameters are shared, read-only);
        ``root_tau`` (frames), ``root_power``, ``root_turn`` and ``root_turn_frames`` change the
        representation's root damping, which nothing learned depends on, and ``root_std`` its
        root-position std rule."""
        rep = self.representation
        if any(k in kw for k in ("root_tau", "root_power", "root_turn", "root_turn_frames")):
            tau, q = float(kw.pop("root_tau", rep.root_tau)), float(kw.pop("root_power", rep.root_power))
            b, w = float(kw.pop("root_turn", rep.root_turn)), float(kw.pop("root_turn_frames", rep.root_turn_frames))
            if (tau, q, b, w) != (rep.root_tau, rep.root_power, rep.root_turn, rep.root_turn_frames):
                rep = rep.with_root_damping(tau, q, b, w)
        if "root_std" in kw:
            rep = rep.with_root_std(kw.pop("root_std") or [])
        o = HLMOptions(**{**self.options.__dict__, **kw})
        return HLMModel(rep, self.params, o, self.meta, self.cond_cov)

    def set_ll_feats(self, feats: Sequence[int] | np.ndarray) -> None:
        """The features of the "ll" row's partial normaliser (``hlm.online.init_state``'s columns 2-3; default's
        long_ll legs baseline, blend/withhlm.py): ascending distinct feature indices; empty: none (the columns
        stay 0 and the step does no extra work).  Nothing else the step computes changes."""
        f = np.unique(np.asarray(feats, dtype=np.int64))
        if f.size and (f[0] < 0 or f[-1] >= self.representation.n_features):
            raise ValueError(f"ll features must be in [0, {self.representation.n_features}) (got {f.tolist()})")
        if np.array_equal(f, self.tables.ll_feats):
            return
        self.tables.ll_feats = f
        self.__dict__.pop("_slot_tables", None)   # the compiled step's tables carry it: made again

    def leg_feats(self, channels: np.ndarray) -> np.ndarray:
        """The features whose every source channel is among ``channels`` (raw channel indices), ascending."""
        fsrc = self.representation._source_index()[0]
        return np.flatnonzero(np.isin(fsrc, np.asarray(channels, dtype=np.int64)).all(1)).astype(np.int64)

    # ---- online core (FeatureModel hooks) ------------------------------------------------------
    def core_init(self, n: int) -> dict[str, np.ndarray]:
        return online.init_state(self.tables, n)

    def step_one(self, slot: int, frame: np.ndarray, observed: np.ndarray) -> Fill | None:
        # encoder, compiled filter and decoder in one call (hlm.fast.step_slot), where the compiled
        # step serves this filter at all
        tabs = self._compiled()
        if tabs is False:
            return None
        done, std, filled, extras = fast.step_slot(tabs, self.pool, slot, frame, observed, online.LIVE, LIVE_STATS,
                                                   self.cond)
        return Fill(done, std, filled, extras)

    def step_batch(self, states: Sequence[FillerState], frames: np.ndarray, observed: np.ndarray,
                   level: int | None = None) -> list[Fill]:
        # FeatureModel.step_batch's lone-stream compiled case (one stream of this model at full
        # quality, (1, C) writable C-contiguous float64 frames and bool mask of the model's width, as
        # the daemon's scheduler gives them) straight to step_one's call, without the seam's
        # conversions: a live stream runs this cold, where each numpy call costs 10-45 us
        # (bench/notebook/hlm9.md).  Anything else goes to FeatureModel.step_batch as before.
        if len(states) == 1 and level is None:
            tabs = self._compiled()
            st = states[0]
            if (tabs is not False and type(st) is FeatureStream and st.model is self
                    and type(frames) is np.ndarray and type(observed) is np.ndarray
                    and frames.dtype == _F64 and observed.dtype == _BOOL and frames.shape == observed.shape == (1, len(self.channels))
                    and frames.flags.c_contiguous and observed.flags.c_contiguous
                    and frames.flags.writeable and observed.flags.writeable):
                done, std, filled, extras = fast.step_slot(tabs, self.pool, st.slot, frames[0], observed[0], online.LIVE,
                                                           LIVE_STATS, self.cond)
                return [Fill(done, std, filled, extras)]
        return super().step_batch(states, frames, observed, level)

    def _compiled(self) -> tuple | bool:
        # the compiled step's tables (hlm.fast.slot_tables) for step_one, step_batch's lone stream,
        # step_rows and step_block, made once (a model is immutable), or False where the compiled step
        # does not serve this filter: another skeleton's root frame is numpy's (mocap.rootframe)
        tabs = self.__dict__.get("_slot_tables")
        if tabs is None:
            rep = self.representation
            ok = fast.usable(self.tables) and not (rep.root is not None and rep.root_mode == "relative")
            tabs = self.__dict__["_slot_tables"] = fast.slot_tables(self.tables, rep) if ok else False
        return tabs

    def step_rows(self, slots: np.ndarray, frames: np.ndarray, observed: np.ndarray) -> tuple | None:
        # a batch's encoders, compiled filters and decoders in one call (hlm.fast.step_rows), where
        # step_one's would serve
        got = self.step_rows_arrays(slots, frames, observed)
        return None if got is None else (got[0], got[1], fast._extras(got[2], got[3]))

    def step_rows_arrays(self, slots: np.ndarray, frames: np.ndarray, observed: np.ndarray) -> tuple | None:
        # step_rows's call with the style posteriors and phases as the kernel's arrays (step_block)
        tabs = self._compiled()
        if tabs is False:
            return None
        return fast.step_rows_arrays(tabs, self.pool, slots, frames, observed, online.LIVE, LIVE_STATS, self.cond)

    def step_block(self, states: Sequence[FillerState], frames: np.ndarray, observed: np.ndarray,
                   level: int | None = None) -> BlockFill:
        # FeatureModel.step_block's compiled case (n > 1 streams of this model at full quality,
        # frames and mask as the daemon's block path gives them) with fewer Python and numpy
        # calls on the way: a live tick runs them cold (bench/notebook/hlm64-7.md).  The pool rows'
        # checks are in the compiled call; where they fail, or anything else is not the usual
        # case, FeatureModel.step_block serves (and names the error).
        n = len(states)
        tabs = self._compiled()
        if (n > 1 and level is None and tabs is not False and type(frames) is np.ndarray and type(observed) is np.ndarray
                and frames.dtype == _F64 and observed.dtype == _BOOL and frames.shape == observed.shape
                and frames.flags.c_contiguous and observed.flags.c_contiguous):
            slots = [s.slot for s in states if type(s) is FeatureStream and s.model is self]
            if len(slots) == n:
                got = fast.step_rows_arrays(tabs, self.pool, np.array(slots, dtype=np.int64), frames, observed,
                                            online.LIVE, LIVE_STATS, self.cond, True)
                if got is not None:  # (None: a stream given twice, which FeatureModel.step_block names)
                    return BlockFill(got[0], got[1], got[4], got[2], got[3])
        return super().step_block(states, frames, observed, level)

    def core_step(self, state: dict[str, np.ndarray], z: np.ndarray, zobs: np.ndarray,
                  rows: np.ndarray | None = None) -> CoreOut:
        if fast.usable(self.tables):
            # the compiled step (hlm.fast), stream by stream: the same arithmetic as below
            zf, sd, ex = fast.step(self.tables, state, z, zobs, rows, online.LIVE, LIVE_STATS)
            if self.cond is not None:
                condfill.correct_many(self.tables, self.cond, state, z, zobs, zf, rows)
            return CoreOut(zf, sd, ex)
        keep: dict = {}
        online.update(self.tables, state, z, zobs, prow=rows, keep=keep, want_ll=False)
        online.accumulate(self.tables, state, z, zobs, prow=rows)
        zf, sd = online.fill(self.tables, state["post"], z, zobs, *online.cycle_stats(state), prow=rows, keep=keep,
                             **online.group_stats(state))
        if self.cond is not None:
            condfill.correct(self.tables, self.cond, state, z, zobs, zf, rows)
        return CoreOut(zf, sd, online.extras(self.tables, state["post"]))

    # ---- offline ----------------------------------------------------------------------------------
    def encode_recording(self, frames: np.ndarray, observed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Features of a whole recording with gaps.  A missing raw channel is held at its last
        completed value only to encode *later* frames' relative root features (never as data)."""
        rep = self.representation
        st = rep.new_state(1)
        T = frames.shape[0]
        Z = np.full((T, rep.n_features), np.nan)
        O = np.zeros((T, rep.n_features), bool)
        for t in range(T):
            z, zo = st.encode(frames[t : t + 1], observed[t : t + 1])
            Z[t], O[t] = z[0], zo[0]
            held = np.where(observed[t], frames[t], st.prev_raw[0])
            st.commit(held[None], observed=observed[t : t + 1])
        return Z, O

    def decode_recording(self, Zf: np.ndarray, Zsd: np.ndarray, frames: np.ndarray, observed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rep = self.representation
        st = rep.new_state(1)
        out = np.empty(frames.shape)
        std = np.empty(frames.shape)
        for t in range(frames.shape[0]):
            f = np.where(observed[t], frames[t], np.nan)[None]
            done, sd = st.finish(Zf[t : t + 1], Zsd[t : t + 1], f, observed[t : t + 1])
            out[t], std[t] = done[0], sd[0]
        return out, std

    def _check_recording(self, frames: np.ndarray, observed: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        frames = np.asarray(frames, dtype=np.float64)
        if frames.ndim != 2 or frames.shape[1] != self.n_channels:
            raise FillerError(f"recording must have shape (n_frames, {self.n_channels}) (got {frames.shape})")
        observed = np.isfinite(frames) if observed is None else np.asarray(observed, dtype=bool)
        if observed.shape != frames.shape:
            raise FillerError(f"observed mask shape {observed.shape} does not match frames {frames.shape}")
        if not np.isfinite(frames[observed]).all():
            raise FillerError("observed values must be finite")
        return frames, observed

    def posterior(self, frames: np.ndarray, observed: np.ndarray | None = None) -> offline.Posterior:
        """Smoothed style and phase posteriors of a raw recording (n_frames, n_channels)."""
        frames, observed = self._check_recording(frames, observed)
        Z, O = self.encode_recording(frames, observed)
        return offline.infer(self.tables, Z, O, self.options.n_iter_d, self.meta.get("hyperparameters", {}).get("eta", 0.1))

    def viterbi(self, frames: np.ndarray, observed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Viterbi alignment: (style (T,), latent-cycle state (T,)) of a raw recording."""
        frames, observed = self._check_recording(frames, observed)
        Z, O = self.encode_recording(frames, observed)
        return offline.viterbi(self.tables, Z, O)

    def fill_smoothed(self, frames: np.ndarray, observed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Offline fill (not causal): eq. (18) with the smoothed posteriors of the whole recording."""
        frames, observed = self._check_recording(frames, observed)
        Z, O = self.encode_recording(frames, observed)
        Zf, Zsd, _ = offline.fill_features(self.tables, Z, O, self.options.n_iter_d, self.cond)
        return self.decode_recording(Zf, Zsd, frames, observed)

    def fill_lagged(self, frames: np.ndarray, observed: np.ndarray | None = None, lag: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Run the fixed-lag stream over a recording and align its output with the input frames."""
        frames, observed = self._check_recording(frames, observed)
        st = self.lag_stream(lag)
        out = []
        for t in range(frames.shape[0]):
            f = st.step(frames[t], observed[t])
            if f is not None:
                out.append(f)
        out += st.flush()
        return np.stack([f.frame for f in out]), np.stack([f.std for f in out])

    def lag_stream(self, lag: int | None = None) -> LagStream:
        return LagStream(self, self.options.lag if lag is None else int(lag))

    # ---- persistence --------------------------------------------------------------------------
    def info(self) -> dict[str, Any]:
        p = self.params
        return {**super().info(), "styles": p.n_styles, "states": p.n_states, "features": self.representation.n_features,
                "root_mode": self.representation.root_mode, "normalize": self.representation.normalize,
                # the step compiled (hlm.fast) or numpy: numba missing, LACUNA_NO_JIT=1, a sandbox
                # forbidding JIT code (systemd MemoryDenyWriteExecute) or a style switch give numpy
                "step": "compiled" if fast.usable(self.tables) else "numpy"}

    def save(self, path: str) -> None:
        p = self.params
        meta = {
            "method": METHOD,
            "channels": list(self.channels),
            "representation": self.representation.to_dict(),
            "options": dict(self.options.__dict__),
            "lam_s": p.lam_s,
            "lam_zbar": p.lam_zbar,
            **{k: v for k, v in self.meta.items() if k not in ("method", "channels", "representation", "options")},
        }
        arrays = {"zbar": p.zbar, "mu": p.mu, "var": p.var, "lam": p.lam, "tau": p.tau, "d": p.d}
        if self.cond_cov is not None:
            arrays["cond_cov"] = self.cond_cov
        modelfile.save_arrays(path, meta, arrays)


def load(path: str, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> HLMModel:
    """Model-file loader registered for method 'hlm' (ModelFileError on bad shapes or values)."""
    from lacuna.modelfile import ModelFileError, require

    rep = Representation.from_dict(meta["representation"])
    if list(meta["channels"]) != rep.channels:
        raise ModelFileError(f"{path}: channel list does not match the representation")
    F = rep.n_features
    mu = require(path, arrays, "mu", (None, None, F))
    C, M, _ = mu.shape
    var = require(path, arrays, "var", (C, M, F))
    lam = require(path, arrays, "lam", (C, F))
    tau = require(path, arrays, "tau", (C,))
    d = require(path, arrays, "d", (None, None))
    zbar = require(path, arrays, "zbar", (M, F))
    if (var <= 0).any() or (lam <= 0).any():
        raise ModelFileError(f"{path}: variances and precisions must be positive")
    if (tau < 0).any() or abs(tau.sum() - 1.0) > 1e-6 or (d <= 0).any() or np.abs(d.sum(1) - 1.0).max() > 1e-6:
        raise ModelFileError(f"{path}: tau and every row of d must be probability vectors")
    params = HLMParams(zbar.astype(float), mu.astype(float), var.astype(float), lam.astype(float), tau.astype(float),
                       d.astype(float), float(meta["lam_s"]), float(meta["lam_zbar"]))
    opts = HLMOptions(**{k: v for k, v in meta.get("options", {}).items() if k in HLMOptions.__dataclass_fields__})
    cov = None
    if "cond_cov" in arrays:  # files written before hlm.condfill have none: the fill is eq. (18) alone
        cov = require(path, arrays, "cond_cov", (C, F, F)).astype(float)
        if not np.isfinite(cov).all() or np.abs(cov - cov.transpose(0, 2, 1)).max() > 1e-9 * max(1.0, np.abs(cov).max()) \
                or (np.linalg.eigvalsh(cov) <= 0).any():
            raise ModelFileError(f"{path}: cond_cov must hold finite symmetric positive definite matrices")
    return HLMModel(rep, params, opts, {k: v for k, v in meta.items() if k in ("hyperparameters", "training")}, cov)


class LagStream:
    """Fixed-lag smoother stream: ``step(frame)`` consumes frame t and returns the Fill of frame
    t - L (None for the first L frames); ``flush()`` returns the last L at the end of a take.

    The filter runs at t (its fill completes the encoder state, exactly as the causal stream);
    a ring buffer keeps the last L + 1 frames' filtered posteriors, emission log-likelihoods and
    inputs, so memory and time per frame are O(L C M J), constant in the stream length.  A second
    representation state decodes the smoothed features of frame t - L.
    """

    def __init__(self, model: HLMModel, lag: int):
        if lag < 0:
            raise ValueError(f"lag must be >= 0 (got {lag})")
        self.model = model
        self.lag = lag
        rep = model.representation
        self.enc = rep.new_state(1)
        self.dec = rep.new_state(1)
        self.core = model.core_init(1)
        C, M = model.tables.shape
        L1 = lag + 1
        self.post = np.zeros((L1, 1, C, M))
        self.ll = np.zeros((L1, 1, C, M))
        self.z = np.zeros((L1, 1, rep.n_features))
        self.zobs = np.zeros((L1, 1, rep.n_features), bool)
        self.raw = np.zeros((L1, model.n_channels))
        self.rawobs = np.zeros((L1, model.n_channels), bool)
        self.n = 0

    def _emit(self, P: np.ndarray, slot: int) -> Fill:
        m = self.model
        zf, sd = online.fill(m.tables, P, self.z[slot], self.zobs[slot], *online.cycle_stats(self.core),
                             **online.group_stats(self.core))
        if m.cond is not None:   # the smoothed posterior's fill, corrected as the causal one is
            condfill.correct(m.tables, m.cond, {**self.core, "post": P}, self.z[slot], self.zobs[slot], zf)
        f = np.where(self.rawobs[slot], self.raw[slot], np.nan)[None]
        done, std = self.dec.finish(zf, sd, f, self.rawobs[slot][None])
        return Fill(done[0], std[0], ~self.rawobs[slot], online.extras(m.tables, P)[0])

    def step(self, frame: np.ndarray | None, observed: np.ndarray | None = None) -> Fill | None:
        m = self.model
        C = m.n_channels
        if frame is None:
            f, obs = np.full(C, np.nan), np.zeros(C, bool)
        else:
            f, obs = check_frame(frame, observed, C)
        z, zo = self.enc.encode(f[None], obs[None])
        ll = online.update(m.tables, self.core, z, zo)
        online.accumulate(m.tables, self.core, z, zo)
        zf, zsd = online.fill(m.tables, self.core["post"], z, zo, *online.cycle_stats(self.core),
                              **online.group_stats(self.core))
        if m.cond is not None:
            condfill.correct(m.tables, m.cond, self.core, z, zo, zf)
        self.enc.finish(zf, zsd, np.where(obs, f, np.nan)[None], obs[None])
        slot = self.n % (self.lag + 1)
        self.post[slot], self.ll[slot], self.z[slot], self.zobs[slot] = self.core["post"], ll, z, zo
        self.raw[slot], self.rawobs[slot] = np.where(obs, f, 0.0), obs
        self.n += 1
        if self.n <= self.lag:
            return None
        order = [(self.n + i) % (self.lag + 1) for i in range(self.lag + 1)]   # oldest first
        P = online.smooth_lag(self.post[order], self.ll[order], self.core["d"], m.tables.style_switch)
        return self._emit(P, order[0])

    def flush(self) -> list[Fill]:
        """Fills of the frames still inside the window, oldest first (smoothed on what exists)."""
        out = []
        k = min(self.n, self.lag)
        order = [(self.n - k + i) % (self.lag + 1) for i in range(k)]
        for i in range(k):
            sub = order[i:]
            P = online.smooth_lag(self.post[sub], self.ll[sub], self.core["d"], self.model.tables.style_switch)
            out.append(self._emit(P, sub[0]))
        return out


modelfile.register_loader(METHOD, load)
