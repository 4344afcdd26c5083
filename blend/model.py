"""The ``default`` filler: three causal predictions of each missing channel, stacked.

For a channel j missing for k frames (k = 1 on the first erased frame), with h_j its last
observed value:

* hold      H = h_j
* velocity  V = h_j + v_j d (1 - d^k) / (1 - d): the channel's smoothed velocity at the gap's
            onset, damped (time constant ``damp_s``), so a short gap continues the motion and a
            long one comes to rest; W the same with the longer ``damp2_s`` (the root keeps
            travelling);
* regress   R = mean_j + E[x_j | observed] + o_j(t): the conditional Gaussian of the missing
            joint angles given the observed ones and their velocities over ``lag_s`` (one
            Gaussian over pose and velocity fitted on training takes), plus an offset o that
            makes R start at h_j (no pop) and decays with time constant ``offset_s``.  When the
            set of observed channels changes mid-gap the offset is re-set so R stays continuous.

The fill is H + w_v(g, t) (V - H) + w_l(g, t) (W - H) + w_r(g, t) (R - H): stacking weights per joint group g and
time since onset t (piecewise linear over ``knots`` seconds), fitted by least squares on the
VALIDATION split (blend.fit); w = 0 is hold, so on the data they were fitted on the blend
cannot be worse than hold in any group or time bin.  Root channels take no regression (their
values are heading- and place-dependent), only hold and velocity: heading continues at its
yaw rate, so a fill follows a turn.

The std of a filled value is c(g, t) * a_j, with a_j the channel's own recent spread (an
exponentially weighted std over ``amp_s`` seconds while it was observed) so that a still
performer gets a tight band and a basketball player a wide one; c is fitted on validation
errors so that 2 std hold 95% of them.  The model is a handful of arrays; a step is O(C) plus
one small matrix-vector product, with the regression matrix cached per pattern of missing
channels (masks recur: a joint group drops out again and again).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from lacuna import modelfile
from lacuna.filler import Fill, FillerState, Model, check_frame
from mocap.representation import is_angle

GROUPS = {
    "root": ("root",),
    "torso": ("lowerback", "upperback", "thorax"),
    "head-neck": ("lowerneck", "upperneck", "head"),
    "left-arm": ("lclavicle", "lhumerus", "lradius", "lwrist", "lhand", "lfingers", "lthumb"),
    "right-arm": ("rclavicle", "rhumerus", "rradius", "rwrist", "rhand", "rfingers", "rthumb"),
    "left-leg": ("lfemur", "ltibia", "lfoot", "ltoes"),
    "right-leg": ("rfemur", "rtibia", "rfoot", "rtoes"),
}
GROUP_NAMES = list(GROUPS) + ["other", "root-pos"]  # root rotations and root translation weigh apart
ROOT_POS = len(GROUP_NAMES) - 1
NO_REGRESSION = (0, ROOT_POS)
KNOTS = (0.0, 1 / 120, 0.05, 0.1, 0.25, 0.5, 1.0, 2.0, 4.0)  # seconds since the gap began


def group_of(channel: str) -> int:
    bone = channel.split(".", 1)[0]
    for i, bones in enumerate(GROUPS.values()):
        if bone in bones or (i == 0 and bone.lower() in ("root", "hips")):
            return ROOT_POS if i == 0 and not is_angle(channel) else i
    return len(GROUPS)


def wrap(x: np.ndarray) -> np.ndarray:
    return (x + 180.0) % 360.0 - 180.0


@dataclass
class Settings:
    """Hyperparameters (chosen on VALIDATION, see docs/BENCHMARKS.md ## default)."""

    fps: float = 120.0
    lag_s: float = 0.05       # velocity features of the regression: x_t - x_{t - lag}
    vel_s: float = 0.02       # smoothing time constant of the onset velocity
    damp_s: float = 0.15      # damping time constant of the velocity extrapolation
    damp2_s: float = 1.0      # the second, slower one
    offset_s: float = 1e9     # decay of the regression's anchoring offset (1e9: never)
    amp_s: float = 1.0        # window of the channel spread that scales the std
    ridge: float = 1e-3       # relative ridge on the observed covariance block
    amp_floor: float = 0.05   # share of the training std added to the spread (a still channel's floor)
    knots: tuple = KNOTS

    def per_frame(self) -> dict[str, float]:
        f = self.fps
        return {"L": max(1, int(round(self.lag_s * f))), "beta": 1.0 - np.exp(-1.0 / max(self.vel_s * f, 1e-9)),
                "d": float(np.exp(-1.0 / max(self.damp_s * f, 1e-9))), "d2": float(np.exp(-1.0 / max(self.damp2_s * f, 1e-9))), "a": float(np.exp(-1.0 / max(self.offset_s * f, 1e-9))),
                "eta": 1.0 - np.exp(-1.0 / max(self.amp_s * f, 1e-9))}


@dataclass
class Weights:
    """Stacking weights and std scale per group (G) and knot (K)."""

    wv: np.ndarray
    wl: np.ndarray
    wr: np.ndarray
    sc: np.ndarray

    @classmethod
    def initial(cls, n_groups: int = len(GROUP_NAMES), n_knots: int = len(KNOTS)) -> "Weights":
        z = np.zeros((n_groups, n_knots))
        return cls(z, z.copy(), z.copy(), np.full((n_groups, n_knots), 1.0))


class DefaultModel(Model):
    method = "default"

    def __init__(self, channels: list[str], mean: np.ndarray, std: np.ndarray, reg_idx: np.ndarray,
                 mu: np.ndarray, cov: np.ndarray, settings: Settings, weights: Weights,
                 meta: dict[str, Any] | None = None):
        self.channels = list(channels)
        C = len(self.channels)
        self.mean_ = np.asarray(mean, float)
        self.std_ = np.asarray(std, float)
        self.reg_idx = np.asarray(reg_idx, int)
        self.mu_ = np.asarray(mu, float)
        self.cov_ = np.asarray(cov, float)
        self.settings = settings
        self.weights = weights
        self.meta = dict(meta or {})
        self.ang = np.array([is_angle(c) for c in self.channels])
        self.group = np.array([group_of(c) for c in self.channels])
        self.knots = np.asarray(settings.knots, float)
        self._pf = settings.per_frame()
        R = len(self.reg_idx)
        self._is_reg = np.zeros(C, bool)
        self._is_reg[self.reg_idx] = True
        self._ridge = settings.ridge * np.mean(np.diag(self.cov_)) if R else 0.0
        self._cache: dict[bytes, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    # ---- regression matrices, cached per missing pattern -------------------------------------
    def regression(self, miss_reg: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For a (R,) bool pattern of missing regression channels: (m, O, B) with m the missing
        positions in reg space, O the observed feature indices (pose and velocity), B (|m|, |O|)."""
        key = miss_reg.tobytes()
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        R = len(self.reg_idx)
        m = np.flatnonzero(miss_reg)
        o = np.flatnonzero(~miss_reg)
        O = np.concatenate([o, o + R])
        if len(O):
            S_oo = self.cov_[np.ix_(O, O)] + self._ridge * np.eye(len(O))
            B = np.linalg.solve(S_oo, self.cov_[np.ix_(O, m)]).T
        else:
            B = np.zeros((len(m), 0))
        if len(self._cache) > 512:
            self._cache.clear()
        self._cache[key] = (m, O, np.ascontiguousarray(B))
        return self._cache[key]

    def knot_weights(self, W: np.ndarray, g: np.ndarray, t: np.ndarray) -> np.ndarray:
        K = len(self.knots)
        p = np.interp(t, self.knots, np.arange(K, dtype=float))
        i = np.minimum(p.astype(int), K - 2)
        f = p - i
        return W[g, i] * (1.0 - f) + W[g, i + 1] * f

    def stream(self) -> "DefaultState":
        return DefaultState(self)

    def with_weights(self, weights: Weights) -> "DefaultModel":
        return DefaultModel(self.channels, self.mean_, self.std_, self.reg_idx, self.mu_, self.cov_, self.settings,
                            weights, self.meta)

    def info(self) -> dict[str, Any]:
        return {**super().info(), "fps": self.settings.fps, "regression_channels": int(len(self.reg_idx))}

    # ---- persistence (npz + JSON; no component model files are referenced: all arrays inline) -
    def save(self, path: str) -> None:
        meta = {**self.meta, "method": self.method, "channels": self.channels,
                "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self.settings).items()},
                "groups": GROUP_NAMES}
        arrays = {"mean": self.mean_, "std": self.std_, "reg_idx": self.reg_idx, "mu": self.mu_, "cov": self.cov_,
                  "wv": self.weights.wv, "wl": self.weights.wl, "wr": self.weights.wr, "sc": self.weights.sc}
        modelfile.save_arrays(path, meta, arrays)

    @classmethod
    def load(cls, path: str, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> "DefaultModel":
        C = len(meta["channels"])
        s = meta.get("settings")
        if not isinstance(s, dict):
            raise modelfile.ModelFileError(f"{path}: default model without 'settings' in its metadata")
        try:
            settings = Settings(**{**s, "knots": tuple(float(k) for k in s.get("knots", KNOTS))})
        except TypeError as e:
            raise modelfile.ModelFileError(f"{path}: default model settings are malformed ({e})") from None
        K = len(settings.knots)
        G = len(GROUP_NAMES)
        reg = modelfile.require(path, arrays, "reg_idx", (None,))
        R = reg.shape[0]
        if R and (reg.min() < 0 or reg.max() >= C):
            raise modelfile.ModelFileError(f"{path}: reg_idx points outside the {C} channels")
        w = Weights(*(modelfile.require(path, arrays, k, (G, K)) for k in ("wv", "wl", "wr", "sc")))
        return cls(meta["channels"], modelfile.require(path, arrays, "mean", (C,)), modelfile.require(path, arrays, "std", (C,)),
                   reg, modelfile.require(path, arrays, "mu", (2 * R,)), modelfile.require(path, arrays, "cov", (2 * R, 2 * R)),
                   settings, w, {k: v for k, v in meta.items() if k not in ("settings", "groups")})


@dataclass
class Components:
    """What one step computed for its missing channels (blend.fit stacks these)."""

    idx: np.ndarray
    k: np.ndarray
    H: np.ndarray
    V: np.ndarray
    W: np.ndarray
    R: np.ndarray
    amp: np.ndarray
    extra: dict = field(default_factory=dict)


class DefaultState(FillerState):
    def __init__(self, model: DefaultModel):
        self.m = model
        C = model.n_channels
        L = model._pf["L"]
        self.last = model.mean_.copy()      # last output (observed or filled), raw units
        self.h = model.mean_.copy()         # last observed value
        self.vel = np.zeros(C)              # smoothed per-frame velocity while observed
        self.v0 = np.zeros(C)               # velocity frozen at the gap's onset
        self.k = np.zeros(C, np.int64)      # frames since onset (0 = observed)
        self.R = model.mean_.copy()         # regression component (continuous across mask changes)
        self.off = np.zeros(C)              # anchoring offset of R
        self.amean = model.mean_.copy()
        self.avar = (model.std_ * 0.5) ** 2
        self.hist = np.repeat(model.mean_[None], L + 2, 0)  # ring of outputs, newest at index pos
        self.pos = 0
        self.miss_key: bytes | None = None
        self.seen = False
        self.collect = False                 # blend.fit sets it and reads ``comp`` after each step
        self.comp: Components | None = None

    def _features(self, x: np.ndarray, x_lag: np.ndarray, O: np.ndarray) -> np.ndarray:
        m = self.m
        ri = m.reg_idx
        R = len(ri)
        po = O[O < R]
        z = np.concatenate([wrap(x[ri[po]] - m.mean_[ri[po]]), wrap(x[ri[O[O >= R] - R]] - x_lag[ri[O[O >= R] - R]])])
        return z - m.mu_[O]

    def step(self, frame, observed=None) -> Fill:
        m = self.m
        pf = m._pf
        f, obs = check_frame(frame, observed, m.n_channels)
        miss = ~obs
        C = m.n_channels
        L = pf["L"]
        n = self.hist.shape[0]
        prev = self.hist[self.pos]
        if obs.any():
            # observed channels: velocity (only across consecutive observations), spread, anchors
            was = (self.k == 0) & obs & self.seen
            dx = np.where(m.ang, wrap(f - self.h), f - self.h)
            self.vel = np.where(was, self.vel + pf["beta"] * (dx - self.vel), self.vel)
            da = np.where(m.ang, wrap(f - self.amean), f - self.amean)
            self.amean = np.where(obs, self.amean + pf["eta"] * da, self.amean)
            self.avar = np.where(obs, (1 - pf["eta"]) * self.avar + pf["eta"] * da * da, self.avar)
            self.h = np.where(obs, f, self.h)
            self.seen = True
        out = np.where(obs, f, 0.0)
        std = np.zeros(C)
        if miss.any():
            onset = miss & (self.k == 0)
            self.v0 = np.where(onset, self.vel, self.v0)
            self.R = np.where(onset, self.h, self.R)
            self.k = np.where(miss, self.k + 1, 0)
            idx = np.flatnonzero(miss)
            kk = self.k[idx]
            d = pf["d"]
            H = self.h[idx]
            V = H + self.v0[idx] * (d * (1.0 - d ** kk) / (1.0 - d))
            d2 = pf["d2"]
            W = H + self.v0[idx] * (d2 * (1.0 - d2 ** kk) / (1.0 - d2))
            Rv = self._regress(f, obs, miss, prev, idx)
            t = kk / m.settings.fps
            g = m.group[idx]
            wv = m.knot_weights(m.weights.wv, g, t)
            wl = m.knot_weights(m.weights.wl, g, t)
            wr = m.knot_weights(m.weights.wr, g, t)
            out[idx] = H + wv * (V - H) + wl * (W - H) + wr * (Rv - H)
            amp = np.sqrt(self.avar[idx] + (m.settings.amp_floor * m.std_[idx]) ** 2)
            std[idx] = m.knot_weights(m.weights.sc, g, t) * amp
            if self.collect:
                self.comp = Components(idx, kk, H, V, W, Rv, amp)
        else:
            self.k[:] = 0
            self.miss_key = None
            self.comp = None
        self.pos = (self.pos + 1) % n
        self.hist[self.pos] = out
        self.last = out
        return Fill(out, std, miss)

    def _regress(self, f, obs, miss, prev, idx) -> np.ndarray:
        """R for the missing channels idx (root and non-angle channels: R = h)."""
        m = self.m
        ri = m.reg_idx
        Rout = self.h[idx].copy()
        miss_reg = miss[ri]
        if not miss_reg.any():
            self.miss_key = None
            return Rout
        mm, O, B = m.regression(miss_reg)
        L = m._pf["L"]
        n = self.hist.shape[0]
        x = np.where(obs, f, self.last)
        x_lag = self.hist[(self.pos - L + 1) % n]       # the output L frames before this one
        r = m.mu_[mm] + B @ self._features(x, x_lag, O)
        cols = ri[mm]
        key = miss_reg.tobytes()
        a = m._pf["a"]
        if key != self.miss_key:
            # the pattern changed: re-anchor so R continues from where it was on the previous frame
            prev = self.hist[self.pos]
            prev_lag = self.hist[(self.pos - L) % n]
            r_prev = m.mu_[mm] + B @ self._features(prev, prev_lag, O)
            self.off[cols] = self.R[cols] - (m.mean_[cols] + r_prev)
            self.miss_key = key
        self.off[cols] *= a
        val = m.mean_[cols] + r + self.off[cols]
        self.R[cols] = val
        pos = np.searchsorted(idx, cols)
        Rout[pos] = val
        return Rout
