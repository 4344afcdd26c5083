"""The guard of ``default``: every stream runs virtual gaps on the joint groups it still sees and
re-weighs its own fill's parts, online, by how they did there.

Whenever a joint group g is fully observed and no virtual gap of it runs (after a pause of 1-61
frames, pseudo-random, since the last one ended; 12 more after a real gap, so its onset velocity
is not the stale one of before that gap), one starts: the group is
treated as missing from this frame on (hold value H = its last value, onset velocity v0, the
regression's anchoring offset, all as a real gap would set them), for up to the last horizon of
``GUARD_S``, or until a channel of g really drops out.  At every horizon k it computes the two
non-hold parts a real fill of g would add k frames after onset, with the stacking weights of
blend.model,

    P = w_v(g, t) (V - H) + w_l(g, t) (W - H)                  (velocity)
    Q = (w_r(g, t) gamma'_g + w_g(g, t) gamma_g) (R - H)        (regression; its matrix is the
                                                                 shadow check's, g from the rest)

and sees the truth's change over hold, y = x - H.  At each horizon k of ``GUARD_S`` (only there: the
regression's prediction costs a matrix-vector product) it adds to that group's and horizon's
decayed sums (time constant ``guard_s``) PP, PQ, QQ, yP, yQ and a count n, and a real gap k frames in fills

    H + lambda_v(g, t) P + lambda_r(g, t) Q,

(lambda_v, lambda_r) the least-squares scales of the two parts on the stream's own virtual gaps,
with a ridge toward (1, 1) of ``guard_n0`` / n times the diagonal (n: virtual gaps that reached
that horizon, decayed) (thin evidence keeps the fitted
weights), each clipped to [0, ``guard_max``].  A run, whose limbs reverse faster than the damping
assumes, finds lambda_v < 1 and falls back on hold and the regression; a performer whose body
moves unlike the training takes finds lambda_r < 1.  No activity label is needed, so it carries
to motion the weights never saw.  ``guard_s`` = 0 turns it off (models saved before it load so).

Here the numpy reference (DefaultState.step_numpy calls it); blend.fast has the same arithmetic.
``st`` is that blend.state.DefaultState, named by its base class: blend.state imports this file.
"""
from __future__ import annotations

import numpy as np

from lacuna.filler import FillerState
from mocap.rootrot import wrap180 as wrap

GUARD_S = (1 / 120, 0.05, 0.1, 0.25, 0.5, 1.0)  # horizons, seconds since a (virtual) gap's onset
NS = 6  # sums per group and horizon: PP, PQ, QQ, yP, yQ, n
SETTLE = 12  # frames a group is observed again before its next virtual gap can start (+ the pause)


def horizons(fps: float) -> np.ndarray:
    """(B,) horizons in frames, increasing, at least 1."""
    return np.array(sorted({max(1, int(round(s * fps))) for s in GUARD_S}), np.int64)


def hat(kk: np.ndarray, hf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frames since onset -> (lower horizon index, weight of the upper one)."""
    B = len(hf)
    if B == 1:
        return np.zeros(len(kk), int), np.zeros(len(kk))
    p = np.interp(np.asarray(kk, float), hf, np.arange(B, dtype=float))
    i = np.minimum(p.astype(int), B - 2)
    return i, p - i


def solve(S: np.ndarray, n0: float, mx: float) -> np.ndarray:
    """(G, B, NS) sums -> (G, B, 2) scales (lambda_v, lambda_r)."""
    pp, pq, qq, yp, yq, n = (S[..., i] for i in range(NS))
    with np.errstate(divide="ignore", invalid="ignore"):
        kap = np.where(n > 0, n0 / np.maximum(n, 1e-300), 0.0)
    a11 = pp * (1 + kap) + 1e-12
    a22 = qq * (1 + kap) + 1e-12
    b1 = yp + kap * pp
    b2 = yq + kap * qq
    det = a11 * a22 - pq * pq
    both = (pp > 1e-9) & (qq > 1e-9) & (det > 1e-12 * a11 * a22)
    with np.errstate(divide="ignore", invalid="ignore"):
        lv = np.where(both, (b1 * a22 - b2 * pq) / np.where(both, det, 1.0), b1 / a11)
        lr = np.where(both, (a11 * b2 - pq * b1) / np.where(both, det, 1.0), b2 / a22)
    lv = np.where((n > 0) & (pp > 1e-9), lv, 1.0)
    lr = np.where((n > 0) & (qq > 1e-9), lr, 1.0)
    return np.stack([np.clip(lv, 0.0, mx), np.clip(lr, 0.0, mx)], -1)


def wait(cnt: int, g: int) -> int:
    """Frames between one virtual gap of group g and the next: 1-61, pseudo-random in the frame count
    (virtual gaps back to back would start at one phase of a gait cycle as long as the cycle lasts)."""
    return 1 + (cnt * 7919 + g * 104729) % 61


def guard_update(st: FillerState, f: np.ndarray, obs: np.ndarray) -> None:
    """Advance every virtual gap by this frame (before the frame updates h and the velocity)."""
    m = st.m
    pf = m._pf
    st.GS *= m.guard_par[0]
    cnt = int(st.sv[5])
    st.sv[5] += 1
    if cnt <= max(pf["L"]) or st.sv[2] == 0:
        return
    Kmax = int(m.guard_h[-1])
    x = np.where(obs, f, st.last)
    zf = None
    for g, cols in enumerate(m.guard_cols):
        if not len(cols):
            continue
        if not obs[cols].all():
            st.vk[g] = -SETTLE - wait(cnt, g)  # after a real gap the velocity needs frames to settle
            continue
        if st.vk[g] >= Kmax:  # done: the next one starts after a pause that no motion's period locks to
            st.vk[g] = -wait(cnt, g)
        if st.vk[g] < 0:
            st.vk[g] += 1
            continue
        new = st.vk[g] == 0
        if new:
            st.vh[cols] = st.h[cols]
            st.vv[cols] = np.clip(st.vn[1, cols] * m.vgain_[cols], -m.vcap[cols], m.vcap[cols])  # the velocity a gap uses
        st.vk[g] += 1
        kk = int(st.vk[g])
        b = m.guard_bin[kk]
        if b < 0:  # scored at the horizons only (a step is then barely dearer than without the guard)
            continue
        t = kk / m.settings.fps
        H = st.vh[cols]
        y = f[cols] - H
        y = np.where(m.ang[cols], wrap(y), y)
        d, d2 = pf["d"], pf["d2"]
        gg = np.full(1, g)
        P = st.vv[cols] * (m.knot_weights(m.weights.wv, gg, t)[0] * (d * (1.0 - d**kk) / (1.0 - d))
                           + m.knot_weights(m.weights.wl, gg, t)[0] * (d2 * (1.0 - d2**kk) / (1.0 - d2)))
        Q = np.zeros(len(cols))
        si = m.guard_sh[g]
        if si >= 0:
            if zf is None:
                zf = st._features(x, 0, np.arange(len(m.mu_)))
            mm = m.sh_m[si, :m.sh_nm[si]]
            O = m.sh_O[si, :m.sh_nO[si]]
            r = m.mu_[mm] + m.sh_B[si, :len(mm), :len(O)] @ zf[O]
            rc = m.reg_idx[mm]
            if new:  # the regression's anchoring offset, decaying from the onset as a real gap's
                st.voff[rc] = wrap(st.vh[rc] - (m.mean_[rc] + r))  # the short way round, as a real gap's
            Rk = m.mean_[rc] + r + st.voff[rc] * pf["a"] ** kk
            gi = np.array([g])
            wq = (m.knot_weights(m.weights.wr, gg, t)[0] * st.gate(gi, weak=True)[0]
                  + m.knot_weights(m.weights.wg, gg, t)[0] * st.gate(gi)[0])
            Q[m.guard_pos[rc]] = wq * wrap(Rk - st.vh[rc])
        st.GS[g, b] += np.array([P @ P, P @ Q, Q @ Q, y @ P, y @ Q, 1.0])


def guard_lambda(st: FillerState, g: np.ndarray, kk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lambda_v, lambda_r) for missing channels of groups g, kk frames since their onset."""
    m = st.m
    L = solve(st.GS, m.guard_par[1], m.guard_par[2])
    i, fr = hat(kk, m.guard_hf)
    lam = L[g, i] * (1.0 - fr)[:, None] + L[g, np.minimum(i + 1, L.shape[1] - 1)] * fr[:, None]
    return lam[:, 0], lam[:, 1]
