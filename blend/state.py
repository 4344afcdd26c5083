"""Per-stream state of ``default`` and its reference (numpy) step; the compiled step is
blend.fast.  See blend.model for what is computed."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from blend.guard import NS, guard_lambda, guard_update
from lacuna.filler import Fill, FillerState, Model, check_frame
from mocap.rootrot import wrap180 as wrap  # (blend.model's wrap, the same arithmetic)


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
    gate: np.ndarray
    weak: np.ndarray
    lam: np.ndarray | None = None   # the guard's scale of the velocity part (None: 1) ...
    lamr: np.ndarray | None = None  # ... and of the regression part
    extra: dict = field(default_factory=dict)


def shrunk(v: np.ndarray, q: np.ndarray, beta: np.ndarray, c: float) -> np.ndarray:
    """The velocity a gap extrapolates (Settings.vel_shrink = c): v^3 / (v^2 + c s^2), a Wiener factor, ~1 for a
    velocity well above its noise and ~0 for the capture's jitter on a still channel.  ``q`` is the mean square
    second difference of the channel's values, 6 sigma^2 for white noise of variance sigma^2 on them (a steady
    acceleration a per frame^2 adds only a^2), and s^2 = 2 beta^2 sigma^2 / (2 - beta) = beta^2 q / (3 (2 - beta))
    the variance that noise leaves in the exponentially smoothed velocity (weight beta).  c = 0: v itself
    (blend.fast._shrunk is the same arithmetic; bench/notebook/vshr-42.md)."""
    if c <= 0:
        return v.copy()
    den = v * v + c * (beta * beta * q / (3.0 * (2.0 - beta)))
    return np.where(den > 0, v * v * v / np.where(den > 0, den, 1.0), v)


class DefaultState(FillerState):
    # ``model`` is the blend.model.DefaultModel whose stream() made this state, named by its base
    # class: blend.model imports this file, so importing it back would make a circle
    def __init__(self, model: Model):
        self.m = model
        C = model.n_channels
        self.last = model.mean_.copy()      # last output (observed or filled), raw units
        self.h = model.mean_.copy()         # last observed value
        self.vel = np.zeros(C)              # smoothed per-frame velocity while observed
        # vel_shrink: the mean square second difference while observed (row 0), the velocity a gap extrapolates,
        # vel shrunk by its noise (row 1; = vel where the setting is off), the last frame difference (row 2; NaN:
        # none since the channel came back)
        self.vn = np.zeros((3, C))
        self.vn[2] = np.nan
        self.v0 = np.zeros(C)               # velocity frozen at the gap's onset
        self.k = np.zeros(C, np.int64)      # frames since onset (0 = observed)
        self.R = model.mean_.copy()         # regression component (continuous across mask changes)
        self.off = np.zeros(C)              # anchoring offset of R
        self.amean = model.mean_.copy()
        self.avar = (model.std_ * 0.5) ** 2
        self.lstd = np.zeros(C)             # the std given with the last output
        # scalars: online calibration's decayed sum of z^2 at gap ends and their count; seen; ring position
        self.sv = np.zeros(6)  # + the frame counter of the shadow check, and the guard's
        # the guard (blend.guard): per group the frames into its virtual gap (0: none, < 0: pausing), per channel the
        # virtual gap's hold value, onset velocity and regression offset; per group x horizon its sums
        G = len(model.guard_cols)
        self.vk = np.zeros(G, np.int64)
        self.vh = np.zeros(C)
        self.vv = np.zeros(C)
        self.voff = np.zeros(C)
        self.GS = np.zeros((G, len(model.guard_h), NS))
        self.GL = np.ones((G, len(model.guard_h), 2))      # the compiled step's scales and scratch
        self.gbuf = np.zeros(2 * C + len(model.mu_))
        G = int(model.group.max()) + 1
        self.ER = np.zeros(G)               # shadow check: decayed squared error of the regression ...
        self.EH = np.zeros(G)               # ... and of the group's own change over the longest lag
        self.NE = np.zeros(G)               # ... and how many checks each group has had (up to gate_n0)
        self.hist = np.repeat(model.mean_[None], max(model._pf["L"]) + 2, 0)  # ring of outputs, newest at sv[3]
        self.miss_key: bytes | None = None
        self.mreg = np.zeros(len(model.reg_idx), bool)   # _step_fast's scratch: the regression channels missing
        self.Rv = np.zeros(C)
        self.collect = False                 # blend.fit sets it and reads ``comp`` after each step
        self.comp: Components | None = None

    def _features(self, x: np.ndarray, back: int, O: np.ndarray) -> np.ndarray:
        """Observed features O of frame x, whose own lagged frames are ``back`` + L frames ago."""
        m = self.m
        ri = m.reg_idx
        xr = x[ri]
        n = self.hist.shape[0]
        pos = int(self.sv[3])
        parts = [xr - m.mean_[ri]] + [xr - self.hist[(pos - L + 1 - back) % n, ri] for L in m._pf["L"]]
        return wrap(np.concatenate(parts))[O] - m.mu_[O]

    def step(self, frame, observed=None) -> Fill:
        f, obs = check_frame(frame, observed, self.m.n_channels)
        if self.m.compiled and not self.collect:
            return self._step_fast(f, obs)
        return self.step_numpy(f, obs)

    def _step_fast(self, f: np.ndarray, obs: np.ndarray) -> Fill:
        C = self.m.n_channels
        out = np.empty(C)
        std = np.empty(C)
        self._step_into(f, obs, out, std)
        return Fill(out, std, ~obs)

    def _step_into(self, f: np.ndarray, obs: np.ndarray, out: np.ndarray, std: np.ndarray) -> None:
        """:meth:`_step_fast` writing the fill and its std into ``out`` and ``std`` (C float64
        each, contiguous: a row of the caller's (n, C) arrays), with no Fill (blend/withhlm.py's
        ``step_block``)."""
        from blend.fast import reg_missing, step_kernel

        m = self.m
        miss_reg = self.mreg
        if reg_missing(obs, m.reg_idx, miss_reg):
            key = miss_reg.tobytes()
            mm, O, B = m.regression(miss_reg, key)
            changed = key != self.miss_key
            self.miss_key = key
            has = True
        else:
            self.miss_key = None
            mm, O, B, changed, has = m._none_i, m._none_i, m._none_B, False, False
        step_kernel(f, obs, m.ang, m.group, m.mean_, m.std_, m.reg_idx, m.mu_, m.knots, m.weights.wv, m.weights.wl,
                    m.weights.wr, m.weights.wg, m.weights.sc, m._par, m._Ls, m.vcap, m.beta, m.vgain_, mm, O, B, has, changed, self.last, self.h, self.vel, self.vn,
                    self.v0, self.k, self.R, self.off, self.amean, self.avar, self.lstd, self.hist, self.sv, out, std,
                    self.Rv, m.sh_g, m.sh_m, m.sh_nm, m.sh_O, m.sh_nO, m.sh_B, self.ER, self.EH, self.NE,
                    m.guard_h, m.guard_hf, m.guard_par, m.guard_cols_flat, m.guard_cols_ptr, m.guard_sh, m.guard_pos,
                    self.vk, self.vh, self.vv, self.voff, self.GS, self.GL, self.gbuf, m.guard_bin)

    def _shadow(self, f: np.ndarray, obs: np.ndarray) -> None:
        """Predict one observed regression group from the others, as if it were missing."""
        m = self.m
        G = len(m.sh_g)
        if not G:
            return
        cnt = int(self.sv[4])
        self.sv[4] += 1
        Lm = max(m._pf["L"])
        if cnt <= Lm:  # the ring does not hold a whole lag of this stream yet
            return
        q = cnt % G
        mm = m.sh_m[q, :m.sh_nm[q]]
        O = m.sh_O[q, :m.sh_nO[q]]
        cols = m.reg_idx[mm]
        if not obs[cols].all():
            return
        x = np.where(obs, f, self.last)
        r = m.mu_[mm] + m.sh_B[q, :len(mm), :len(O)] @ self._features(x, 0, O)
        n = self.hist.shape[0]
        g = m.sh_g[q]
        lam = m.settings.gate_decay
        self.ER[g] = lam * self.ER[g] + float(np.sum(wrap(x[cols] - m.mean_[cols] - r) ** 2))
        self.EH[g] = lam * self.EH[g] + float(np.sum(wrap(x[cols] - self.hist[(int(self.sv[3]) - Lm + 1) % n, cols]) ** 2))
        self.NE[g] = min(self.NE[g] + 1.0, m.settings.gate_n0)

    def gate(self, g: np.ndarray, weak: bool = False) -> np.ndarray:
        rho = (self.ER[g] + 1e-9) / (self.EH[g] + 1e-9)
        s = self.m.settings
        if s.gate_n0 > 0:  # a group with few checks of its own: the stream's other groups speak for it
            w = np.minimum(self.NE[g] / s.gate_n0, 1.0)
            rho = w * rho + (1.0 - w) * (self.ER.sum() + 1e-9) / (self.EH.sum() + 1e-9)
        return 1.0 / (1.0 + (rho / (s.gate_rho_weak if weak else s.gate_rho)) ** 2)

    def step_numpy(self, f: np.ndarray, obs: np.ndarray) -> Fill:
        """The reference step (numpy); ``f, obs`` already checked."""
        m = self.m
        pf = m._pf
        miss = ~obs
        C = m.n_channels
        n = self.hist.shape[0]
        if self.sv[2] == 0 and obs.any():  # the first frame: the ring starts from it, not from the training mean
            self.hist[:] = np.where(obs, f, self.hist[0])
        self._shadow(f, obs)
        prev = self.hist[int(self.sv[3])]
        if m.guard_on:
            guard_update(self, f, obs)
        if obs.any():
            # observed channels: velocity (only across consecutive observations), spread, anchors
            was = (self.k == 0) & obs & (self.sv[2] > 0)
            dx = np.where(m.ang, wrap(f - self.h), f - self.h)
            if m.settings.vel_shrink > 0:  # (the jitter's estimate, read only by vel_shrink)
                d2 = dx - self.vn[2]  # the second difference, where the frame before was a difference too
                self.vn[0] = np.where(was & np.isfinite(d2), (1 - pf["eta"]) * self.vn[0] + pf["eta"] * d2 * d2, self.vn[0])
                self.vn[2] = np.where(obs, np.where(was, dx, np.nan), self.vn[2])
            self.vel = np.where(was, self.vel + m.beta * (dx - self.vel), self.vel)
            self.vn[1] = np.where(was, shrunk(self.vel, self.vn[0], m.beta, m.settings.vel_shrink), self.vn[1])
            da = np.where(m.ang, wrap(f - self.amean), f - self.amean)
            self.amean = np.where(obs, self.amean + pf["eta"] * da, self.amean)
            self.avar = np.where(obs, (1 - pf["eta"]) * self.avar + pf["eta"] * da * da, self.avar)
            self.h = np.where(obs, f, self.h)
            # online calibration: where a gap just ended, how far off was the last fill, in its std?
            back = obs & (self.k > 0)
            if back.any():
                z = (np.where(m.ang[back], wrap(f[back] - self.last[back]), f[back] - self.last[back])
                     / np.maximum(self.lstd[back], 1e-9))
                lam = m.settings.cal_decay ** back.sum()
                self.sv[0] = lam * self.sv[0] + float(np.sum(np.minimum(z * z, 25.0)))
                self.sv[1] = lam * self.sv[1] + float(back.sum())
            self.sv[2] = 1.0
        out = np.where(obs, f, 0.0)
        std = np.zeros(C)
        if miss.any():
            onset = miss & (self.k == 0)
            self.v0 = np.where(onset, np.clip(self.vn[1] * m.vgain_, -m.vcap, m.vcap), self.v0)
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
            gate = self.gate(g)
            weak = self.gate(g, weak=True)
            wr = m.knot_weights(m.weights.wr, g, t) * weak + m.knot_weights(m.weights.wg, g, t) * gate
            lv, lr = guard_lambda(self, g, kk) if m.guard_on else (np.ones(len(idx)), np.ones(len(idx)))
            out[idx] = H + lv * (wv * (V - H) + wl * (W - H)) + lr * wr * (Rv - H)
            amp = np.sqrt(self.avar[idx] + (m.settings.amp_floor * m.std_[idx]) ** 2)
            P = m.settings.cal_prior
            scale = min(max(np.sqrt((P + self.sv[0]) / (P + self.sv[1])), 0.33), 3.0) if self.sv[1] else 1.0
            std[idx] = m.knot_weights(m.weights.sc, g, t) * amp * scale
            if self.collect:
                self.comp = Components(idx, kk, H, V, W, Rv, amp, gate, weak, lv, lr)
        else:
            self.k[:] = 0
            self.miss_key = None
            self.comp = None
        pos = (int(self.sv[3]) + 1) % n
        self.sv[3] = pos
        self.hist[pos] = out
        self.last = out.copy()
        self.lstd = std.copy()
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
        key = miss_reg.tobytes()
        mm, O, B = m.regression(miss_reg, key)
        x = np.where(obs, f, self.last)
        r = m.mu_[mm] + B @ self._features(x, 0, O)
        cols = ri[mm]
        a = m._pf["a"]
        if key != self.miss_key:
            # the pattern changed: re-anchor so R continues from where it was on the previous frame
            r_prev = m.mu_[mm] + B @ self._features(self.hist[int(self.sv[3])], 1, O)
            self.off[cols] = wrap(self.R[cols] - (m.mean_[cols] + r_prev))  # the short way round (an angle)
            self.miss_key = key
        self.off[cols] *= a
        val = m.mean_[cols] + r + self.off[cols]
        self.R[cols] = val
        pos = np.searchsorted(idx, cols)
        Rout[pos] = self.h[cols] + wrap(val - self.h[cols])  # on the branch of the last value: never 360 away
        return Rout
