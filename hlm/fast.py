"""A compiled (numba) step of the online HLM filter for one stream: the same arithmetic as the
lone-stream numpy path of ``hlm.online`` (``_predict_one``, ``_update_one``, ``accumulate``,
``fill``, ``extras``), in one call instead of a few hundred numpy calls.

Used by ``HLMModel.core_step`` for a batch of one stream when ``lacuna.jit.enabled()`` and the
filter has no transition adaptation and no change of style (the default ``hlm`` and the
faithful kappa = 0 filter); everything else, and every batch of several streams, runs the numpy
code, which stays the reference: ``tests/test_hlm_fast.py`` checks the two agree to 1e-9 frame
by frame on real motion.  ``LACUNA_NO_JIT=1`` turns the compiled path off.

Equations (numbered as in ``hlm.online``): the prediction is the cyclic jump transition of
eq. (1), the update multiplies by the expected emission of eq. (10) on the prediction's support,
the fill is eq. (18) with the joint posterior; the stream-cycle statistics are ``hlm.streamcycle``'s.
"""
from __future__ import annotations

import math

import numpy as np

from lacuna.jit import enabled, jit as _jit  # noqa: F401  (enabled: re-exported for callers)


@_jit
def _step(post, first, prior, d_pop, M, z, zobs, fused_t, mu, bin0, bin1, bin_a, kappa, kappa_g, nb,
          D, W, G, GW, lam_rows, var_q, pack, cos, sin, live, live_stats, out, sd, style):  # pragma: no cover - compiled
    CM = post.shape[0]
    F = z.shape[0]
    C = CM // M
    J = d_pop.shape[0]
    # ---- predict: p(c, m | x_<t) = sum_j d_j post(c, m - j) (the cycle wraps within a style)
    pr = np.zeros(CM)
    if first:
        for s in range(CM):
            pr[s] = prior[s]
    else:
        for s in range(CM):
            ps = post[s]
            if ps != 0.0:
                base = s - s % M
                m = s % M
                for j in range(J):
                    pr[base + (m + j + 1) % M] += d_pop[j] * ps
    # ---- update on the support of the prediction: emission terms [o x, o, o x^2] . fused row
    anyobs = False
    for f in range(F):
        if zobs[f]:
            anyobs = True
    k = 0
    rows = np.empty(CM, np.int64)
    for s in range(CM):
        if pr[s] > 0.0:
            rows[k] = s
            k += 1
    llp = np.zeros(k)
    if anyobs:
        v = np.zeros(3 * F)
        for f in range(F):
            if zobs[f]:
                x = z[f]
                v[f] = x
                v[F + f] = 1.0
                v[2 * F + f] = x * x
        top = -np.inf
        for i in range(k):
            acc = 0.0
            row = fused_t[rows[i]]
            for f in range(3 * F):
                acc += row[f] * v[f]
            llp[i] = acc
            if acc > top:
                top = acc
        for i in range(k):
            llp[i] = math.exp(llp[i] - top)
    else:
        for i in range(k):
            llp[i] = 1.0
    tot = 0.0
    for i in range(k):
        llp[i] *= pr[rows[i]]
        tot += llp[i]
    for s in range(CM):
        post[s] = 0.0
    pmax = 0.0
    for i in range(k):
        p = llp[i] / tot
        post[rows[i]] = p
        if p > pmax:
            pmax = p
    # ---- stream-cycle statistics (kappa > 0), from the live states of the new posterior
    if kappa > 0.0 and anyobs:
        for i in range(k):
            s = rows[i]
            p = post[s]
            if not p > live_stats * pmax:
                continue
            b0, b1, a = bin0[s], bin1[s], bin_a[s]
            w0, w1 = p * (1.0 - a), p * a
            c = s // M
            for f in range(F):
                if zobs[f]:
                    dev = z[f] - mu[s, f]
                    D[b0, f] += w0 * dev
                    D[b1, f] += w1 * dev
                    W[b0, f] += w0
                    W[b1, f] += w1
                    G[c, f] += p * dev
                    GW[c, f] += p
    # ---- fill the missing features from the live states (eq. 18 with the joint posterior)
    anymiss = False
    for f in range(F):
        out[f] = z[f]
        sd[f] = 0.0
        if not zobs[f]:
            anymiss = True
    if anymiss:
        ptot = 0.0
        for i in range(k):
            p = post[rows[i]]
            if p > live * pmax:
                ptot += p
        num = np.zeros(F)
        den = np.zeros(F)
        mean = np.zeros(F)
        m2 = np.zeros(F)
        for i in range(k):
            s = rows[i]
            p = post[s]
            if not p > live * pmax:
                continue
            p /= ptot
            if kappa > 0.0:
                b0, b1, a = bin0[s], bin1[s], bin_a[s]
                c = s // M
                for f in range(F):
                    if zobs[f]:
                        continue
                    # the stream's offset at this state: knot offsets E (streamcycle.knot_offsets)
                    # interpolated between the state's two knots
                    if kappa_g > 0.0:
                        g = G[c, f] / (kappa_g + GW[c, f])
                        e0 = g + (D[b0, f] - W[b0, f] * g) / (kappa + W[b0, f])
                        e1 = g + (D[b1, f] - W[b1, f] * g) / (kappa + W[b1, f])
                    else:
                        e0 = D[b0, f] / (kappa + W[b0, f])
                        e1 = D[b1, f] / (kappa + W[b1, f])
                    u = mu[s, f] + (1.0 - a) * e0 + a * e1
                    lam = lam_rows[s, f]
                    num[f] += p * lam * u
                    den[f] += p * lam
                    mean[f] += p * u
                    m2[f] += p * (u * u + var_q[s, f])
            else:
                row = pack[s]
                for f in range(F):
                    if zobs[f]:
                        continue
                    num[f] += p * row[f]
                    den[f] += p * row[F + f]
                    mean[f] += p * row[2 * F + f]
                    m2[f] += p * row[3 * F + f]
        for f in range(F):
            if not zobs[f]:
                val = num[f] / den[f]
                var = max(m2[f] - mean[f] * mean[f], 0.0) + (mean[f] - val) ** 2
                out[f] = val
                sd[f] = math.sqrt(var)
    # ---- extras: the style posterior and the circular mean of the phase
    for c in range(C):
        style[c] = 0.0
    sc = 0.0
    ss = 0.0
    for s in range(CM):
        p = post[s]
        if p != 0.0:
            style[s // M] += p
            sc += p * cos[s % M]
            ss += p * sin[s % M]
    return (math.atan2(ss, sc) / (2.0 * math.pi)) % 1.0


def usable(tab) -> bool:
    """Whether the compiled step computes what ``hlm.online`` would for this filter."""
    return enabled() and tab.adapt_rate == 0.0 and tab.style_switch == 0.0


def step_one(tab, state: dict[str, np.ndarray], z: np.ndarray, zobs: np.ndarray, r: int | None = None,
             live: float = 1e-10, live_stats: float = 1e-4) -> tuple[np.ndarray, np.ndarray, dict]:
    """One frame of one stream: z, zobs (1, F).  ``state`` is ``hlm.online.init_state``'s for n = 1;
    with ``r`` its D, W, G, GW are a state pool's and the stream owns their row r.  Updates the
    state in place; returns (z completed (1, F), std (1, F), extras)."""
    C, M = tab.shape
    F = z.shape[1]
    post = state["post"].reshape(-1)
    first = bool(state["t"][0] == 0)
    if tab.kappa > 0.0:
        i = 0 if r is None else int(r)
        D, W, G, GW = state["D"][i], state["W"][i], state["G"][i], state["GW"][i]
    else:
        D = W = np.zeros((1, F))
        G = GW = np.zeros((1, F))
    out = np.empty((1, F))
    sd = np.empty((1, F))
    style = np.empty(C)
    post1 = np.ascontiguousarray(post)
    phase = _step(post1, first, tab.prior_flat, tab.d_pop, M, np.ascontiguousarray(z[0], dtype=np.float64),
                  np.ascontiguousarray(zobs[0], dtype=np.bool_), tab.em.fused_t, tab.mu, tab.bin0, tab.bin1,
                  tab.bin_a, tab.kappa, tab.kappa_global, tab.n_bins, D, W, G, GW, tab.lam_rows, tab.var_q,
                  tab.pack, tab.cos, tab.sin, live, live_stats, out[0], sd[0], style)
    if post1 is not post:
        post[:] = post1
    state["t"] += 1
    return out, sd, {"style": style.tolist(), "phase": float(phase)}
