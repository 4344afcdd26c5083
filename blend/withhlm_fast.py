"""``default-hlm``'s per-frame mixing compiled with numba: the arithmetic of
``WithHLMModel._mix_numpy`` (blend/withhlm.py) channel by channel for one stream in one call,
without the ~25 numpy calls on 62-wide arrays that made the mixing cost more than either expert.
tests/test_default_hlm_fast.py checks the two against each other to 1e-9 on real motion.  Used
where ``lacuna.jit.enabled()``; else the numpy mixing serves.
"""
from __future__ import annotations

import numpy as np

from lacuna.jit import jit


@jit
def _wrap(x):
    return (x + 180.0) % 360.0 - 180.0


@jit
def observed_finite(F, O):
    """True when every observed value of the (n, C) batch is finite (blend.model.checked_batch's
    test, in one compiled call instead of four numpy ones: a frame 8 ms after the last pays each
    numpy call's cold start, bench/notebook/mixlat-4.md)."""
    for i in range(F.shape[0]):
        for j in range(F.shape[1]):
            if O[i, j] and not np.isfinite(F[i, j]):
                return False
    return True


@jit
def shadow_counts(O, nonpos, sgroup, gmiss):
    """Channels really missing (root translation aside), and per shadow group its missing channels
    into ``gmiss`` (``sgroup[j]``: channel j's index into SHADOW_GROUPS, -1 for none)."""
    n = 0
    for g in range(gmiss.shape[0]):
        gmiss[g] = 0.0
    for j in range(O.shape[0]):
        if not O[j]:
            if nonpos[j]:
                n += 1
            if sgroup[j] >= 0:
                gmiss[sgroup[j]] += 1.0
    return n


@jit
def mix_row(F, O, HO, D, Dsd, H, Hsd, T, has_twin, ang, group, W, S, t_edges, qb, anchor, k, o, out, std,
            knots, wk, pop, prel, pdecay, rp, vp, e, bdecay, wb):
    """One stream's frame: ``out``/``std`` from the experts' fills (D, Dsd), (H, Hsd); the state's
    frames since onset ``k`` and anchoring offsets ``o`` updated in place.  Returns the shadow
    check's squared errors of the HLM and of the twin T on the hidden angles (O and not HO) and
    how many there were (T is read only where ``has_twin``).

    Smoothing (blend/withhlm.py's module doc, "Smooth"): with ``knots`` (one per time bin, its
    centre in frames since onset) S, and W too where ``wk``, are read linearly between the knots
    instead of as steps at the bin edges; with ``pop`` > 0, from a gap's third frame on, the fill y may depart from its
    own linear course (last value plus last step, ``rp`` + ``vp``) by at most ``pop`` + ``prel``
    |last step| a frame, the excess going into an offset ``e`` that decays by ``pdecay`` a frame
    (rp, vp, e updated in place).  With ``bdecay`` > 0 the band's share ``wb`` (updated in place)
    follows w from the gap's second frame on as wb += (w - wb) (1 - bdecay): the std's mixture uses
    it, the fill does not.  Without knots, with pop = 0 and bdecay = 0 this is the unsmoothed
    mixing, bit for bit."""
    eh = 0.0
    e0 = 0.0
    nh = 0
    NT = t_edges.shape[0]
    NK = knots.shape[0]
    for j in range(F.shape[0]):
        if O[j]:
            k[j] = 0
            out[j] = F[j]
            std[j] = 0.0
            if has_twin and ang[j] and not HO[j]:
                a = _wrap(H[j] - F[j])
                b = _wrap(T[j] - F[j])
                eh += a * a
                e0 += b * b
                nh += 1
            continue
        kk = k[j] + 1
        k[j] = kk
        d = H[j] - D[j]
        if ang[j]:
            d = _wrap(d)
        if kk == 1:
            o[j] = -d
        diff = d + o[j] * anchor ** (kk - 1) if anchor > 0.0 else d
        g = group[j]
        tb = 0
        while tb < NT and t_edges[tb] <= kk:
            tb += 1
        w = W[g, tb, qb]
        sc = S[g, tb]
        if NK > 0:   # between the knots: S, and W too where wk
            i = 0
            f = 0.0
            if kk >= knots[NK - 1]:
                i = NK - 2
                f = 1.0
            elif kk > knots[0]:
                while knots[i + 1] <= kk:
                    i += 1
                f = (kk - knots[i]) / (knots[i + 1] - knots[i])
            sc = S[g, i] * (1.0 - f) + S[g, i + 1] * f
            if wk:
                w = W[g, i, qb] * (1.0 - f) + W[g, i + 1, qb] * f
        y = D[j] + w * diff
        if pop > 0.0:   # the pop limit on the fill (module doc of blend/withhlm.py, "Smooth")
            if kk == 1:
                rp[j] = y
                vp[j] = 0.0
                e[j] = 0.0
            elif kk == 2:
                vp[j] = y - rp[j]
                rp[j] = y
                e[j] = 0.0
            else:
                jump = y - (rp[j] + vp[j])
                lim = pop + prel * abs(vp[j])
                x = 0.0
                if jump > lim:
                    x = jump - lim
                elif jump < -lim:
                    x = jump + lim
                e[j] = e[j] * pdecay - x
                vp[j] = y - rp[j] - x
                rp[j] = y
            out[j] = y + e[j]
        else:
            out[j] = y
        if bdecay > 0.0:   # the band's share, low-passed
            if kk == 1:
                wb[j] = w
            else:
                wb[j] = wb[j] + (w - wb[j]) * (1.0 - bdecay)
            w = wb[j]
        var = (1.0 - w) * Dsd[j] * Dsd[j] + w * Hsd[j] * Hsd[j] + w * (1.0 - w) * diff * diff
        std[j] = sc * np.sqrt(var)
    return eh, e0, nh


RATE_FTZ = 1e-150   # a decayed |dx| sum below this is 0: a channel held exactly still decays into
# subnormal floats after ~85,000 frames (12 minutes at 120 Hz), each operation on which costs ~100x


@jit
def _ftz(v):
    """``v``, or 0 below RATE_FTZ (withhlm.py's numpy path applies the same rule, so both agree)."""
    return v if v >= RATE_FTZ else 0.0


@jit
def rate_band(F, O, ang, std, rpar, ref, rst):
    """The band's rate (blend/withhlm.py's module doc, "Rate") after ``mix_row`` on one stream's
    frame, called only where it is on: ``rpar`` = (decay, a, lo, hi).  Each missing channel's
    ``std`` is times clip((rate / ref)^a, lo, hi), rate = rst[0] / rst[1] from its frames before
    this one (1 where rst[1] < 1 or ref <= 0); each observed channel's decayed sums of |dx| over
    consecutive observed frames and of 1 (``rst`` rows 0, 1; its last value and whether the last
    frame was observed, rows 2, 3) are updated in place.  Off, it is not called: ``mix_row``'s
    arguments and cost are as before the rate."""
    rdecay = rpar[0]
    ra = rpar[1]
    for j in range(F.shape[0]):
        if O[j]:
            if rst[3, j] > 0.0:
                dx = F[j] - rst[2, j]
                if ang[j]:
                    dx = _wrap(dx)
                rst[0, j] = _ftz(rst[0, j] * rdecay + abs(dx))
                rst[1, j] = rst[1, j] * rdecay + 1.0
            rst[2, j] = F[j]
            rst[3, j] = 1.0
        else:
            rst[3, j] = 0.0
            if rst[1, j] >= 1.0 and ref[j] > 0.0:
                m = (rst[0, j] / rst[1, j] / ref[j]) ** ra
                std[j] = std[j] * min(max(m, rpar[2]), rpar[3])


@jit
def stream_rate(ang, ref, rst, buf):
    """The stream's rate (blend/withhlm.py's module doc, "Band q"): the median over angle channels
    with ref > 0 and at least one value's weight of history (rst[1] >= 1) of rst[0] / rst[1] / ref;
    -1 where no channel has any.  ``buf``: scratch of the channels' length."""
    n = 0
    for j in range(ang.shape[0]):
        if ang[j] and ref[j] > 0.0 and rst[1, j] >= 1.0:
            buf[n] = rst[0, j] / rst[1, j] / ref[j]
            n += 1
    if n == 0:
        return -1.0
    return np.median(buf[:n])


@jit
def q_band(F, O, ang, std, k, M, qb, bdecay, mb, gpar, ref, rst, rdecay, upd, buf):
    """band_q after ``mix_row`` on one stream's frame, called only where it is on (module doc,
    "Band q"): each missing channel j's ``std`` times mb[j], the low-passed (over ``bdecay``, from
    the gap's first frame k[j] == 1) target 1 + (M[j, qb] - 1) gate, gate from the stream's rate
    read before this frame's update (gpar = (r0, r1, gated): 1 for rate <= r0, 0 for >= r1, linear
    between, 0 without a rate; gated 0: 1).  With ``upd`` (the band's rate off: rate_band is not
    called) the observed channels' rate sums ``rst`` are updated here, as rate_band does."""
    gate = 1.0
    if gpar[2] > 0.0:
        r = stream_rate(ang, ref, rst, buf)
        if r < 0.0:
            gate = 0.0
        elif r <= gpar[0]:
            gate = 1.0
        elif r >= gpar[1]:
            gate = 0.0
        else:
            gate = (gpar[1] - r) / (gpar[1] - gpar[0])
    for j in range(F.shape[0]):
        if O[j]:
            if upd:   # rate_band's update, written out: as a shared jit helper (even inline="always") this
                # kernel cost 1.4x more a call (bench/band_mixcost.py --on q, 2026-12-04: 8.3 vs 5.7 us)
                if rst[3, j] > 0.0:
                    dx = F[j] - rst[2, j]
                    if ang[j]:
                        dx = _wrap(dx)
                    rst[0, j] = _ftz(rst[0, j] * rdecay + abs(dx))
                    rst[1, j] = rst[1, j] * rdecay + 1.0
                rst[2, j] = F[j]
                rst[3, j] = 1.0
        else:
            if upd:
                rst[3, j] = 0.0
            m = 1.0 + (M[j, qb] - 1.0) * gate
            if k[j] == 1 or bdecay <= 0.0:
                mb[j] = m
            else:
                mb[j] = mb[j] + (m - mb[j]) * (1.0 - bdecay)
            std[j] = std[j] * mb[j]


@jit
def _obs_median(O, ang, ref, num, den, buf):
    """The median over observed angle channels with ref > 0 and at least one value's weight of
    history (den >= 1) of num / den / ref; -1 where none (blend/withhlm.py's module doc, "Pace")."""
    n = 0
    for j in range(ang.shape[0]):
        if O[j] and ang[j] and ref[j] > 0.0 and den[j] >= 1.0:
            buf[n] = num[j] / den[j] / ref[j]
            n += 1
    if n == 0:
        return -1.0
    return np.median(buf[:n])


@jit
def pace_row(F, O, ang, out, k, ref, ps, pz, py, pr, ppar, buf):
    """The pace (blend/withhlm.py's module doc, "Pace") after ``mix_row`` (and the band's kernels) on
    one stream's frame, called only where it is on: ``ppar`` = (fast decay, slow decay, kfac, a).  First
    each observed channel's decayed sums of |dx| over consecutive observed frames and of 1, fast
    (``ps`` rows 0, 1) and slow (rows 2, 3), its last value (row 4) and whether it was observed the
    frame before (row 5) are updated; then R = the observed body's fast rate now (_obs_median of rows
    0, 1).  A missing channel j on its gap's first frame (k[j] == 1) keeps pr[j] = the observed body's
    slow rate (rows 2, 3) now, and its fill starts from its last value; on every frame of the gap the
    fill y (``out[j]``) moves its own step times s = clip(R / min(kfac pr[j], a), 0, 1) (a = 0: no
    such level, kfac pr[j] alone; s = 1 where either
    rate is undefined, or the channel has no last value): z = z_prev + s wrap(y - y_prev), z written to
    ``out[j]``; pz, py hold z and y."""
    fd = ppar[0]
    sd = ppar[1]
    kf = ppar[2]
    pa = ppar[3]
    for j in range(F.shape[0]):
        if O[j]:
            if ps[5, j] > 0.0:
                dx = F[j] - ps[4, j]
                if ang[j]:
                    dx = _wrap(dx)
                dx = abs(dx)
                ps[0, j] = _ftz(ps[0, j] * fd + dx)
                ps[1, j] = ps[1, j] * fd + 1.0
                ps[2, j] = _ftz(ps[2, j] * sd + dx)
                ps[3, j] = ps[3, j] * sd + 1.0
            ps[4, j] = F[j]
    r = _obs_median(O, ang, ref, ps[0], ps[1], buf)
    r0 = -2.0
    for j in range(F.shape[0]):
        if O[j]:
            ps[5, j] = 1.0
            continue
        y = out[j]
        if k[j] == 1:
            if r0 == -2.0:
                r0 = _obs_median(O, ang, ref, ps[2], ps[3], buf)
            pr[j] = r0
            if ps[5, j] > 0.0:   # observed the frame before: its last value is where the gap starts
                pz[j] = ps[4, j]
                py[j] = ps[4, j]
            else:   # never observed: nothing to start from; the fill as it is
                pr[j] = -1.0
                pz[j] = y
                py[j] = y
        ps[5, j] = 0.0
        s = 1.0
        if r >= 0.0 and pr[j] > 0.0:
            den = kf * pr[j]
            if pa > 0.0 and pa < den:
                den = pa
            s = min(max(r / den, 0.0), 1.0)
        d = y - py[j]
        if ang[j]:
            d = _wrap(d)
        pz[j] = pz[j] + s * d
        py[j] = y
        out[j] = pz[j]
