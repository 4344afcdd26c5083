"""The ``default`` filler: three causal predictions of each missing channel, stacked.

For a channel j missing for k frames (k = 1 on the first erased frame), with h_j its last
observed value:

* hold      H = h_j
* velocity  V = h_j + v_j d (1 - d^k) / (1 - d): the channel's smoothed velocity at the gap's
            onset, damped (time constant ``damp_s``), so a short gap continues the motion and a
            long one comes to rest; W the same with the longer ``damp2_s`` (the root keeps
            travelling);
* regress   R = mean_j + E[x_j | observed] + o_j(t): the conditional Gaussian of the missing
            joint angles given the observed ones and their changes over each lag of ``lags_s``
            (one Gaussian over pose and changes fitted on training takes), plus an offset o that
            makes R start at h_j (no pop) and decays with time constant ``offset_s``.  When the
            set of observed channels changes mid-gap the offset is re-set so R stays continuous.

The fill is H + w_v(g, t) (V - H) + w_l(g, t) (W - H) + (w_r(g, t) gamma'_g + w_g(g, t) gamma_g) (R - H): stacking weights per joint group g and
time since onset t (piecewise linear over ``knots`` seconds), fitted by least squares on the
VALIDATION split (blend.fit); w = 0 is hold, and the fit re-weighs any (activity, time since
onset) cell, and any cell of the root's own angles, that is worse than hold there.  Root channels take no regression (their
values are heading- and place-dependent), only hold and velocity: heading continues at its
yaw rate, so a fill follows a turn.

The regression is gated per stream by how well it predicts channels that are still observed:
every frame one regression group that is observed is predicted from the others as if it were
missing, and rho_g = sum (error of that prediction)^2 / sum (the group's own change over the
longest lag)^2, decayed, and gamma_g = 1 / (1 + (rho_g / gate_rho)^2) weighs the gated part
w_g of the regression (gamma'_g, the same with ``gate_rho_weak``, its other part), so a stream whose body does not move the way the training takes did
falls back on hold and velocity.

The guard (blend.guard) scales the velocity part (w_v, w_l terms) and the regression part of every
fill by per-stream factors lambda_v(g, t), lambda_r(g, t) in [0, 1], learnt online from virtual
gaps on the groups the stream still observes (``guard_s`` = 0: off, both 1).

The std of a filled value is c(g, t) * a_j * s, with a_j the channel's own recent spread (an
exponentially weighted std over ``amp_s`` seconds while it was observed) so that a still
performer gets a tight band and a basketball player a wide one; c is fitted on validation
errors so that 2 std hold 95% of them; s is the stream's own calibration, learnt online: each
time a gap ends the filler sees how far its last fill was from the returning value, in units of
the std it gave, and s = sqrt(mean z^2) over those values (with ``cal_prior`` pseudo-values of 1).  The model is a handful of arrays; a step is O(C) plus
one small matrix-vector product, with the regression matrix cached per pattern of missing
channels (masks recur: a joint group drops out again and again).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from blend import guard
from blend.groups import GROUP_NAMES, GROUPS, NO_REGRESSION, ROOT_POS, group_of, model_groups  # noqa: F401
from blend.state import DefaultState
from lacuna import modelfile
from lacuna.filler import FillerError, Model
from mocap.representation import is_angle

# seconds since the gap began; beyond the last knot the weights stay as they are there (the calibration gaps
# end at 2 s: a knot further out would only be extrapolated)
CACHE_PATTERNS = 512  # regression matrices kept, one per pattern of missing channels
KNOTS = (0.0, 1 / 120, 0.05, 0.1, 0.25, 0.5, 1.0, 2.0)


def wrap(x: np.ndarray) -> np.ndarray:
    return (x + 180.0) % 360.0 - 180.0


@dataclass
class Settings:
    """Hyperparameters (chosen on VALIDATION, see docs/BENCHMARKS.md ## default)."""

    fps: float = 120.0
    lags_s: tuple = (0.05,)   # change features of the regression: x_t - x_{t - lag} for each lag
    vel_s: float = 0.02       # smoothing time constant of the onset velocity
    vel_root_s: float = 0.02  # the same for the root's channels (longer: the heading's rate over a gait cycle)
    damp_s: float = 0.15      # damping time constant of the velocity extrapolation
    damp2_s: float = 1.0      # the second, slower one
    offset_s: float = 1e9     # decay of the regression's anchoring offset (1e9: never)
    amp_s: float = 1.0        # window of the channel spread that scales the std
    ridge: float = 1e-3       # relative ridge on the observed covariance block
    amp_floor: float = 0.05   # share of the training std added to the spread (a still channel's floor)
    cal_prior: float = 5.0    # online std calibration: pseudo-count of z^2 = 1 (chosen on validation: 5, 15, off)
    cal_decay: float = 0.995  # ... and the decay per value seen at a gap's end
    gate_rho: float = 1e9     # regression gate gamma = 1 / (1 + (rho / gate_rho)^2), rho the stream's shadow
                              # error ratio (1e9: gamma = 1)
    gate_decay: float = 0.9   # decay of the shadow error sums per check (one group checked per frame)
    gate_rho_weak: float = 1e9  # the same gate, weaker, on w_r (1e9: w_r ungated)
    gate_n0: float = 0.0      # shadow checks of a group before its own rho alone gates it: with n < gate_n0 checks
                              # so far its rho is (n rho_g + (gate_n0 - n) rho_stream) / gate_n0, rho_stream the
                              # ratio of all groups' sums (1 before any check): a group not yet seen is gated by how
                              # the regression predicts the rest of this stream (0: off, its prior is rho = 1;
                              # files written before it load so)
    vcap_mult: float = 1e9    # onset velocity capped at this many training RMS changes per frame (1e9: no cap)
    vel_gain: float = 0.0     # 1: each channel's onset velocity scaled by its training gain (vgain); 0: not
    vel_shrink: float = 0.0   # c: the onset velocity v becomes v^3 / (v^2 + c s^2), s^2 the variance the stream's
                              # jitter (read off its second differences) leaves in the smoothed velocity
                              # (blend.state.shrunk): a velocity inside it is not extrapolated (0: off; files
                              # written before it load so)
    knots: tuple = KNOTS
    guard_s: float = 0.0      # the guard (blend.guard): decay time constant of its evidence, seconds (0: off)
    guard_n0: float = 120.0   # ... its ridge toward lambda = 1: guard_n0 / n times the diagonal (n: virtual gaps seen)
    guard_max: float = 1.0    # ... the largest lambda (1: the guard only shrinks toward hold)

    def per_frame(self) -> dict[str, float]:
        f = self.fps
        return {"L": tuple(max(1, int(round(lag * f))) for lag in self.lags_s), "beta": 1.0 - np.exp(-1.0 / max(self.vel_s * f, 1e-9)),
                "d": float(np.exp(-1.0 / max(self.damp_s * f, 1e-9))), "d2": float(np.exp(-1.0 / max(self.damp2_s * f, 1e-9))), "a": float(np.exp(-1.0 / max(self.offset_s * f, 1e-9))),
                "eta": 1.0 - np.exp(-1.0 / max(self.amp_s * f, 1e-9))}


@dataclass
class Weights:
    """Stacking weights and std scale per group (G) and knot (K)."""

    wv: np.ndarray
    wl: np.ndarray
    wr: np.ndarray
    wg: np.ndarray
    sc: np.ndarray

    @classmethod
    def initial(cls, n_groups: int = len(GROUP_NAMES), n_knots: int = len(KNOTS)) -> Weights:
        z = np.zeros((n_groups, n_knots))
        return cls(z, z.copy(), z.copy(), z.copy(), np.full((n_groups, n_knots), 1.0))


class DefaultModel(Model):
    method = "default"

    def __init__(self, channels: list[str], mean: np.ndarray, std: np.ndarray, reg_idx: np.ndarray,
                 mu: np.ndarray, cov: np.ndarray, settings: Settings, weights: Weights,
                 meta: dict[str, Any] | None = None, vrms: np.ndarray | None = None, vgain: np.ndarray | None = None,
                 group: np.ndarray | None = None):
        self.channels = list(channels)
        C = len(self.channels)
        # each channel's weight row (blend.groups): given (a model file's record), else through the skeleton map
        self.group = model_groups(self.channels, group)
        self.mean_ = np.asarray(mean, float)
        self.std_ = np.asarray(std, float)
        # RMS per-frame change of each channel in training: the onset velocity is capped at vcap_mult of it
        # (Euler angles of the root swing through gimbal flips faster than any limb; a fill must not follow)
        self.vrms_ = np.full(C, 1e9) if vrms is None else np.asarray(vrms, float)
        self.vcap = settings.vcap_mult * self.vrms_
        # how far each channel's smoothed velocity predicts its motion 0.1 s on (training least squares, in
        # [0, 1]): a jittery thumb's velocity is noise and is not extrapolated
        self.vgain_ = np.ones(C) if vgain is None or not settings.vel_gain else np.asarray(vgain, float)
        root = np.isin(self.group, NO_REGRESSION)
        self.beta = np.where(root, 1.0 - np.exp(-1.0 / max(settings.vel_root_s * settings.fps, 1e-9)),
                             1.0 - np.exp(-1.0 / max(settings.vel_s * settings.fps, 1e-9)))
        self.reg_idx = np.asarray(reg_idx, int)
        self.mu_ = np.asarray(mu, float)
        self.cov_ = np.asarray(cov, float)
        self.settings = settings
        self.weights = weights
        self.meta = dict(meta or {})
        self.ang = np.array([is_angle(c) for c in self.channels])
        self.knots = np.asarray(settings.knots, float)
        self._pf = settings.per_frame()
        R = len(self.reg_idx)
        self._is_reg = np.zeros(C, bool)
        self._is_reg[self.reg_idx] = True
        self._ridge = settings.ridge * np.mean(np.diag(self.cov_)) if R else 0.0
        self._cache: dict[bytes, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        pf = self._pf
        self._par = np.array([pf["beta"], pf["d"], pf["d2"], pf["a"], pf["eta"], settings.fps, settings.amp_floor,
                              settings.cal_prior, settings.cal_decay, settings.gate_rho, settings.gate_decay, settings.gate_rho_weak,
                              settings.gate_n0, settings.vel_shrink])
        self._Ls = np.array(pf["L"], np.int64)
        self._none_i = np.zeros(0, np.int64)
        self._none_B = np.zeros((0, 0))
        self._shadow()
        self.guard_on = settings.guard_s > 0
        self.guard_h = guard.horizons(settings.fps)
        self.guard_hf = self.guard_h.astype(float)
        self.guard_bin = np.full(int(self.guard_h[-1]) + 1, -1, np.int64)  # frames since onset -> horizon index
        self.guard_bin[self.guard_h] = np.arange(len(self.guard_h))
        Gn = int(self.group.max()) + 1 if C else 0
        self.guard_cols = [np.flatnonzero(self.group == g) for g in range(Gn)]
        self.guard_cols_flat = np.concatenate(self.guard_cols + [np.zeros(0, np.int64)]).astype(np.int64)
        self.guard_cols_ptr = np.cumsum([0] + [len(c) for c in self.guard_cols]).astype(np.int64)
        self.guard_pos = np.zeros(C, np.int64)
        for cols in self.guard_cols:
            self.guard_pos[cols] = np.arange(len(cols))
        self.guard_sh = np.full(Gn, -1, np.int64)
        for i, g in enumerate(self.sh_g):
            self.guard_sh[g] = i
        self.guard_par = np.array([float(np.exp(-1.0 / max(settings.guard_s * settings.fps, 1e-9))) if self.guard_on else 1.0,
                                   settings.guard_n0, settings.guard_max, 1.0 if self.guard_on else 0.0])
        from lacuna import jit

        self.compiled = jit.enabled()

    def _shadow(self) -> None:
        """Per regression group g: the matrix predicting g's channels from every other regression
        channel (pose and changes), for the stream's shadow check (padded arrays for the kernel)."""
        ri = self.reg_idx
        gs = sorted({int(g) for g in self.group[ri]})
        mats = []
        for g in gs:
            miss = self.group[ri] == g
            mats.append((g,) + self.regression(miss))
        self._cache.clear()
        G = len(mats)
        mx_m = max((len(m) for _, m, _, _ in mats), default=0)
        mx_o = max((len(o) for _, _, o, _ in mats), default=0)
        self.sh_g = np.array([g for g, _, _, _ in mats], np.int64)
        self.sh_m = np.zeros((G, mx_m), np.int64)
        self.sh_nm = np.zeros(G, np.int64)
        self.sh_O = np.zeros((G, mx_o), np.int64)
        self.sh_nO = np.zeros(G, np.int64)
        self.sh_B = np.zeros((G, mx_m, mx_o))
        for i, (_g, m, O, B) in enumerate(mats):
            self.sh_m[i, :len(m)] = m
            self.sh_nm[i] = len(m)
            self.sh_O[i, :len(O)] = O
            self.sh_nO[i] = len(O)
            self.sh_B[i, :len(m), :len(O)] = B

    # ---- regression matrices, cached per missing pattern -------------------------------------
    def regression(self, miss_reg: np.ndarray, key: bytes | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For a (R,) bool pattern of missing regression channels: (m, O, B) with m the missing
        positions in reg space, O the observed feature indices (pose and velocity), B (|m|, |O|).
        ``key``: ``miss_reg.tobytes()`` where the caller has it already."""
        if key is None:
            key = miss_reg.tobytes()
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        R = len(self.reg_idx)
        m = np.flatnonzero(miss_reg)
        o = np.flatnonzero(~miss_reg)
        O = np.concatenate([o + b * R for b in range(1 + len(self.settings.lags_s))])
        if len(O):
            S_oo = self.cov_[np.ix_(O, O)] + self._ridge * np.eye(len(O))
            B = np.linalg.solve(S_oo, self.cov_[np.ix_(O, m)]).T
        else:
            B = np.zeros((len(m), 0))
        if len(self._cache) >= CACHE_PATTERNS:
            # the oldest pattern goes (dicts keep insertion order), not every pattern at once: many
            # streams' masks would otherwise all be solved again on the serving thread together
            del self._cache[next(iter(self._cache))]
        hit = self._cache[key] = (m, O, np.ascontiguousarray(B))
        return hit

    def knot_weights(self, W: np.ndarray, g: np.ndarray, t: np.ndarray) -> np.ndarray:
        K = len(self.knots)
        p = np.interp(t, self.knots, np.arange(K, dtype=float))
        i = np.minimum(p.astype(int), K - 2)
        f = p - i
        return W[g, i] * (1.0 - f) + W[g, i + 1] * f

    def stream(self):
        return DefaultState(self)

    def step_batch(self, states, frames, observed):
        """Many streams: one check of the whole batch, then each stream's compiled step."""
        if not self.compiled or not states or not all(isinstance(s, DefaultState) and s.m is self and not s.collect
                                                      for s in states):
            return super().step_batch(states, frames, observed)
        F, O = checked_batch(len(states), self.n_channels, frames, observed)
        return [s._step_fast(F[i], O[i]) for i, s in enumerate(states)]

    def with_weights(self, weights: Weights) -> DefaultModel:
        return DefaultModel(self.channels, self.mean_, self.std_, self.reg_idx, self.mu_, self.cov_, self.settings,
                            weights, self.meta, self.vrms_, self.vgain_, self.group)

    def with_settings(self, **changes: Any) -> DefaultModel:
        """This model with some Settings changed (those read per step, e.g. vel_shrink; not the fitted arrays')."""
        return DefaultModel(self.channels, self.mean_, self.std_, self.reg_idx, self.mu_, self.cov_, replace(self.settings, **changes),
                            self.weights, self.meta, self.vrms_, self.vgain_, self.group)

    def info(self) -> dict[str, Any]:
        return {**super().info(), "fps": self.settings.fps, "regression_channels": int(len(self.reg_idx))}

    # ---- persistence (npz + JSON; no component model files are referenced: all arrays inline) -
    def save(self, path: str) -> None:
        meta = {**self.meta, "method": self.method, "channels": self.channels,
                "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self.settings).items()},
                "groups": GROUP_NAMES}
        arrays = {"mean": self.mean_, "std": self.std_, "reg_idx": self.reg_idx, "mu": self.mu_, "cov": self.cov_, "vrms": self.vrms_, "vgain": self.vgain_,
                  "group": self.group, "wv": self.weights.wv, "wl": self.weights.wl, "wr": self.weights.wr, "wg": self.weights.wg, "sc": self.weights.sc}
        modelfile.save_arrays(path, meta, arrays)

    @classmethod
    def load(cls, path: str, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> DefaultModel:
        C = len(meta["channels"])
        s = meta.get("settings")
        if not isinstance(s, dict):
            raise modelfile.ModelFileError(f"{path}: default model without 'settings' in its metadata")
        try:
            settings = Settings(**{**s, "knots": tuple(float(k) for k in s.get("knots", KNOTS)),
                                   "lags_s": tuple(float(k) for k in s.get("lags_s", (0.05,)))})
        except TypeError as e:
            raise modelfile.ModelFileError(f"{path}: default model settings are malformed ({e})") from None
        if not (isinstance(settings.vel_shrink, (int, float)) and np.isfinite(settings.vel_shrink) and settings.vel_shrink >= 0):
            raise modelfile.ModelFileError(f"{path}: default model setting vel_shrink must be a finite number >= 0 "
                                           f"(got {settings.vel_shrink!r})")
        K = len(settings.knots)
        G = len(GROUP_NAMES)
        reg = modelfile.require(path, arrays, "reg_idx", (None,))
        R = reg.shape[0]
        nb = 1 + len(settings.lags_s)
        if R and (reg.min() < 0 or reg.max() >= C):
            raise modelfile.ModelFileError(f"{path}: reg_idx points outside the {C} channels")
        w = Weights(*(modelfile.require(path, arrays, k, (G, K)) for k in ("wv", "wl", "wr", "wg", "sc")))
        return cls(meta["channels"], modelfile.require(path, arrays, "mean", (C,)), modelfile.require(path, arrays, "std", (C,)),
                   reg, modelfile.require(path, arrays, "mu", (nb * R,)), modelfile.require(path, arrays, "cov", (nb * R, nb * R)),
                   settings, w, {k: v for k, v in meta.items() if k not in ("settings", "groups")},
                   modelfile.require(path, arrays, "vrms", (C,)), modelfile.require(path, arrays, "vgain", (C,)),
                   model_groups(meta["channels"], arrays.get("group", "legacy"), path))


def checked_batch(n: int, n_channels: int, frames: Any, observed: Any) -> tuple[np.ndarray, np.ndarray]:
    """A batch's frames (float64) and masks (bool) as contiguous (n, C) arrays, or FillerError
    saying what is wrong (the shape, or a NaN/inf where a value is observed)."""
    F = np.ascontiguousarray(frames, dtype=np.float64)
    O = np.ascontiguousarray(observed, dtype=bool)
    if F.shape != (n, n_channels) or O.shape != F.shape:
        raise FillerError(f"a batch of {n} streams needs frames and masks of shape "
                          f"({n}, {n_channels}) (got {F.shape} and {O.shape})")
    if (O & ~np.isfinite(F)).any():
        i, j = np.argwhere(O & ~np.isfinite(F))[0]
        raise FillerError(f"observed values must be finite (got NaN/inf in stream {i} at channel {j})")
    return F, O
