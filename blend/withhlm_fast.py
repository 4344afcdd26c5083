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
def mix_row(F, O, HO, D, Dsd, H, Hsd, T, has_twin, ang, group, W, S, t_edges, qb, anchor, k, o, out, std):
    """One stream's frame: ``out``/``std`` from the experts' fills (D, Dsd), (H, Hsd); the state's
    frames since onset ``k`` and anchoring offsets ``o`` updated in place.  Returns the shadow
    check's squared errors of the HLM and of the twin T on the hidden angles (O and not HO) and
    how many there were (T is read only where ``has_twin``)."""
    eh = 0.0
    e0 = 0.0
    nh = 0
    NT = t_edges.shape[0]
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
        tb = 0
        while tb < NT and t_edges[tb] <= kk:
            tb += 1
        g = group[j]
        w = W[g, tb, qb]
        out[j] = D[j] + w * diff
        var = (1.0 - w) * Dsd[j] * Dsd[j] + w * Hsd[j] * Hsd[j] + w * (1.0 - w) * diff * diff
        std[j] = S[g, tb] * np.sqrt(var)
    return eh, e0, nh
