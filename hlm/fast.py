"""A compiled (numba) step of the online HLM filter, stream by stream: the same arithmetic as
the lone-stream numpy path of ``hlm.online`` (``_predict_one``, ``_update_one``, ``accumulate``,
``fill``, ``extras``), in one call per batch instead of a few hundred numpy calls per stream (or
the batched gathers of the numpy batch path, which cost ~25 us per stream at 64).

Used by ``HLMModel.core_step``, ``step_one`` (``step_slot``: one stream) and ``step_rows``
(``step_rows``: a daemon tick's streams, encoder, filter and decoder in one call on their pool
rows) when ``lacuna.jit.enabled()`` and the filter has no transition adaptation and no change of
style (the default ``hlm`` and the faithful kappa = 0 filter); the others run the numpy code,
which stays the reference: ``tests/test_hlm_fast.py`` checks the two agree to 1e-9 frame by
frame on real motion, one stream and batches (contiguous and scattered pool slots), and that a
batch in one call gives each stream the bits it gets alone.  ``LACUNA_NO_JIT=1`` turns the
compiled path off.

The step visits only the support of the posterior and of the prediction (~20 of C*M = 560
states on a walk), in working arrays made once per batch, with the emission dot products summed
in SIMD lanes (``lacuna.jit.jit_sums``; everything else in the sequential order of the numpy
reference's loops).  Nothing is pruned: every state with non-zero mass is carried.

Equations (numbered as in ``hlm.online``): the prediction is the cyclic jump transition of
eq. (1), the update multiplies by the expected emission of eq. (10) on the prediction's support,
the fill is eq. (18) with the joint posterior; the stream-cycle statistics are ``hlm.streamcycle``'s.
"""
from __future__ import annotations

import math

import numpy as np

from hlm.condfill import STYLE_LIVE, correct1
from lacuna.jit import enabled  # noqa: F401  (enabled: re-exported for callers)
from lacuna.jit import jit as _jit
from lacuna.jit import jit_sums as _jit_sums
from lacuna.jit import numba as _numba
from mocap import fastrepr
from mocap.fastrepr import encode1, finish1

_I64, _F64, _BOOL = np.dtype(np.int64), np.dtype(np.float64), np.dtype(np.bool_)


@_jit
def scratch(CM, F, M):  # pragma: no cover - compiled
    """The step's working arrays, made once per batch (``_step_in``): pr (CM,) all zero between
    steps; then llp (CM,), v (3F,), num/den/mean/m2 (F,) each, the partial normaliser's terms (CM,), in one float block; rows and the
    touched prediction entries (CM,) each, the observed and the missing features (F,) each, and
    each state's style and phase (CM,) each (s // M, s % M: an integer division costs tens of cycles), in one int
    block."""
    ix = np.empty(4 * CM + 2 * F, np.int64)
    s = 0
    for c in range(CM // M):
        for m in range(M):
            ix[2 * CM + 2 * F + s] = c
            ix[3 * CM + 2 * F + s] = m
            s += 1
    return np.zeros(3 * CM + 7 * F), ix


@_jit_sums
def _dot(T, s, v):  # pragma: no cover - compiled
    """T[s] . v, summed in SIMD lanes (``lacuna.jit.jit_sums``): an emission's log-likelihood
    term to ~1e-16 relative of the sequential sum (tests/test_hlm_fast*.py hold the step to
    1e-9 of numpy's, whose matrix products sum in their own order).  (T indexed in place: a row
    view would cost numba an atomic reference count up and down, a support state each.)"""
    acc = 0.0
    for f in range(v.shape[0]):
        acc += T[s, f] * v[f]
    return acc


@_jit
def _nonzero(x, out, positive):  # pragma: no cover - compiled
    """The s with x[s] != 0 (positive: x[s] > 0), ascending, into out; returns how many.  What a
    pass testing each entry finds (the predict's sources, the update's support: ~20 of C*M = 560
    entries), sixteen entries at a time: a block whose bits are all those of +0.0 or -0.0 (their
    bits shifted left by one, OR-ed, are 0; a NaN's or any other number's are not) holds none, and
    only the others are tested entry by entry."""
    n = x.shape[0]
    xi = x.view(np.int64)
    k = 0
    b = 0
    while b + 16 <= n:
        acc = 0
        for j in range(b, b + 16):
            acc |= xi[j] << 1
        if acc != 0:
            for s in range(b, b + 16):
                if (x[s] > 0.0) if positive else (x[s] != 0.0):
                    out[k] = s
                    k += 1
        b += 16
    for s in range(b, n):
        if (x[s] > 0.0) if positive else (x[s] != 0.0):
            out[k] = s
            k += 1
    return k


@_jit
def _step_in(post, first, prior, d_pop, M, z, zobs, fused_t, mu, bin0, bin1, bin_a, kappa, kappa_g, nb,
             D, W, G, GW, lam_rows, var_q, pack, cos, sin, live, live_stats, out, sd, style, fs, ix, lf):  # pragma: no cover - compiled
    """The step on the posterior's and the prediction's support only, in the working arrays fs,
    ix (``scratch``; fs[:CM] must be zero and is left zero).  The same operations in the same
    order as a pass over all C*M states: the states are visited ascending, and the terms it
    would skip (zero mass, a missing feature's zero emission term) add exactly nothing.
    Returns (the phase, k, ll, no, lll, nl): the new posterior is exactly 0 outside the k states ix[:k]
    (ascending), the support ``condfill.correct1`` visits; ll the step's normaliser, log p(z_t,o | z_<t,o)
    (0 with nothing observed), and no the features observed (``hlm.online.init_state``'s "ll" row); lll, nl
    the same over the observed features among lf (the table's ll_feats) only, on the same support (0, 0 with
    none: no extra work where lf is empty)."""
    CM = post.shape[0]
    F = z.shape[0]
    C = CM // M
    J = d_pop.shape[0]
    pr = fs[:CM]
    llp = fs[CM : 2 * CM]
    v = fs[2 * CM : 2 * CM + 3 * F]
    num = fs[2 * CM + 3 * F : 2 * CM + 4 * F]
    den = fs[2 * CM + 4 * F : 2 * CM + 5 * F]
    mean = fs[2 * CM + 5 * F : 2 * CM + 6 * F]
    m2 = fs[2 * CM + 6 * F : 2 * CM + 7 * F]
    lpl = fs[2 * CM + 7 * F : 3 * CM + 7 * F]
    rows = ix[:CM]
    tch = ix[CM : 2 * CM]
    fo = ix[2 * CM : 2 * CM + F]
    fm = ix[2 * CM + F : 2 * CM + 2 * F]
    cof = ix[2 * CM + 2 * F : 3 * CM + 2 * F]
    mof = ix[3 * CM + 2 * F :]
    # ---- predict: p(c, m | x_<t) = sum_j d_j post(c, m - j) (the cycle wraps within a style)
    nt = 0
    if first:
        for s in range(CM):
            pr[s] = prior[s]
            post[s] = 0.0
            tch[s] = s
        nt = CM
    else:
        ns = _nonzero(post, rows, False)  # (rows: free until the update's support)
        for i in range(ns):
            s = rows[i]
            ps = post[s]
            post[s] = 0.0
            m = mof[s]
            base = s - m
            for j in range(J):
                g = m + j + 1
                if g >= M:  # (J <= M: one wrap at most)
                    g -= M
                g += base
                if pr[g] == 0.0:
                    tch[nt] = g  # (to zero it after: a target may be listed twice if a term added 0)
                    nt += 1
                pr[g] += d_pop[j] * ps
    # ---- update on the support of the prediction: emission terms [o x, o, o x^2] . fused row
    k = _nonzero(pr, rows, True)  # (ascending: one pass costs less than sorting the touched targets)
    no = 0
    nm = 0
    for f in range(F):
        if zobs[f]:
            fo[no] = f
            no += 1
        else:
            fm[nm] = f
            nm += 1
    if no > 0:
        for f in range(3 * F):
            v[f] = 0.0
        for i in range(no):
            f = fo[i]
            x = z[f]
            v[f] = x
            v[F + f] = 1.0
            v[2 * F + f] = x * x
        top = -np.inf
        for i in range(k):
            acc = _dot(fused_t, rows[i], v)
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
    lln = top + math.log(tot) if no > 0 else 0.0
    # ---- the partial normaliser over lf's observed features (the diagonal emission's terms of those
    # features only), on the same support, from the prediction (pr, still whole here)
    lll = 0.0
    nl = 0
    if no > 0:
        for j in range(lf.shape[0]):
            if zobs[lf[j]]:
                nl += 1
    if nl > 0:
        topl = -np.inf
        for i in range(k):
            s = rows[i]
            acc = 0.0
            for j in range(lf.shape[0]):
                f = lf[j]
                if zobs[f]:
                    x = z[f]
                    acc += fused_t[s, f] * x + fused_t[s, F + f] + fused_t[s, 2 * F + f] * (x * x)
            lpl[i] = acc
            if acc > topl:
                topl = acc
        totl = 0.0
        for i in range(k):
            totl += pr[rows[i]] * math.exp(lpl[i] - topl)
        lll = topl + math.log(totl)
    for i in range(nt):
        pr[tch[i]] = 0.0
    pmax = 0.0
    for i in range(k):
        p = llp[i] / tot
        post[rows[i]] = p
        if p > pmax:
            pmax = p
    # ---- stream-cycle statistics (kappa > 0), from the live states of the new posterior
    if kappa > 0.0 and no > 0:
        for i in range(k):
            s = rows[i]
            p = post[s]
            if not p > live_stats * pmax:
                continue
            b0, b1, a = bin0[s], bin1[s], bin_a[s]
            w0, w1 = p * (1.0 - a), p * a
            c = cof[s]
            # each observed feature's D[b0] += w0 dev, D[b1] += w1 dev, W[b0] += w0, W[b1] += w1,
            # G[c] += p dev, GW[c] += p, in that order for a feature (b0 may be b1), over every
            # feature in SIMD lanes (a missing one's entries stored back as they were: the same
            # bits as a loop over the observed ones), one pair of rows a loop (the compiler checks
            # two rows for overlap, not six)
            for f in range(F):
                dev = z[f] - mu[s, f]
                x0 = D[b0, f] + w0 * dev
                D[b0, f] = x0 if zobs[f] else D[b0, f]
                x1 = D[b1, f] + w1 * dev
                D[b1, f] = x1 if zobs[f] else D[b1, f]
            for f in range(F):
                x0 = W[b0, f] + w0
                W[b0, f] = x0 if zobs[f] else W[b0, f]
                x1 = W[b1, f] + w1
                W[b1, f] = x1 if zobs[f] else W[b1, f]
            for f in range(F):
                dev = z[f] - mu[s, f]
                x0 = G[c, f] + p * dev
                G[c, f] = x0 if zobs[f] else G[c, f]
                x1 = GW[c, f] + p
                GW[c, f] = x1 if zobs[f] else GW[c, f]
    # ---- fill the missing features from the live states (eq. 18 with the joint posterior)
    for f in range(F):
        out[f] = z[f]
        sd[f] = 0.0
    if no < F:
        ptot = 0.0
        for i in range(k):
            p = post[rows[i]]
            if p > live * pmax:
                ptot += p
        for f in range(F):
            num[f] = 0.0
            den[f] = 0.0
            mean[f] = 0.0
            m2[f] = 0.0
        for i in range(k):
            s = rows[i]
            p = post[s]
            if not p > live * pmax:
                continue
            p /= ptot
            if kappa > 0.0:
                b0, b1, a = bin0[s], bin1[s], bin_a[s]
                c = cof[s]
                for j in range(nm):
                    f = fm[j]
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
                for j in range(nm):
                    f = fm[j]
                    num[f] += p * pack[s, f]
                    den[f] += p * pack[s, F + f]
                    mean[f] += p * pack[s, 2 * F + f]
                    m2[f] += p * pack[s, 3 * F + f]
        for f in range(F):
            if not zobs[f]:
                val = num[f] / den[f]
                var = max(m2[f] - mean[f] * mean[f], 0.0) + (mean[f] - val) ** 2
                out[f] = val
                sd[f] = math.sqrt(var)
    # ---- extras: the style posterior and the circular mean of the phase (the posterior is
    # zero off rows)
    for c in range(C):
        style[c] = 0.0
    sc = 0.0
    ss = 0.0
    for i in range(k):
        s = rows[i]
        p = post[s]
        if p != 0.0:
            style[cof[s]] += p
            sc += p * cos[mof[s]]
            ss += p * sin[mof[s]]
    return (math.atan2(ss, sc) / (2.0 * math.pi)) % 1.0, k, lln, no, lll, nl


def usable(tab) -> bool:
    """Whether the compiled step computes what ``hlm.online`` would for this filter."""
    return enabled() and tab.adapt_rate == 0.0 and tab.style_switch == 0.0


@_jit
def _step_many(post, first, prior, d_pop, M, z, zobs, fused_t, mu, bin0, bin1, bin_a, kappa, kappa_g, nb,
               D, W, G, GW, prow, lam_rows, var_q, pack, cos, sin, live, live_stats, out, sd, style, phase, ll, lf):  # pragma: no cover - compiled
    fs, ix = scratch(post.shape[1], z.shape[1], M)  # (once for the batch)
    for i in range(post.shape[0]):
        r = prow[i]
        phase[i], k, ll[i, 0], ll[i, 1], ll[i, 2], ll[i, 3] = _step_in(
            post[i], first[i], prior, d_pop, M, z[i], zobs[i], fused_t, mu, bin0, bin1, bin_a, kappa, kappa_g, nb, D[r], W[r],
            G[r], GW[r], lam_rows, var_q, pack, cos, sin, live, live_stats, out[i], sd[i], style[i], fs, ix, lf)


def step(tab, state: dict[str, np.ndarray], z: np.ndarray, zobs: np.ndarray, rows: np.ndarray | None = None,
         live: float = 1e-10, live_stats: float = 1e-4) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """One frame of each of n streams, stream by stream in one compiled call: z, zobs (n, F).
    ``state`` is ``hlm.online.init_state``'s for the n streams; with ``rows`` (n,) its D, W, G,
    GW are a state pool's and stream i owns their row rows[i] (``mocap.feature_model``).
    Updates the state in place; returns (z completed (n, F), std (n, F), extras per stream)."""
    C, M = tab.shape
    n, F = z.shape
    post = state["post"].reshape(n, -1)
    post1 = np.ascontiguousarray(post)
    first = state["t"] == 0
    if tab.kappa > 0.0:
        D, W, G, GW = state["D"], state["W"], state["G"], state["GW"]
        prow = np.arange(n, dtype=np.int64) if rows is None else np.asarray(rows, dtype=np.int64)
    else:
        D = W = G = GW = np.zeros((1, 1, F))
        prow = np.zeros(n, dtype=np.int64)
    out = np.empty((n, F))
    sd = np.empty((n, F))
    style = np.empty((n, C))
    phase = np.empty(n)
    ll = state["ll"] if "ll" in state else np.zeros((n, 4))
    _step_many(post1, first, tab.prior_flat, tab.d_pop, M, np.ascontiguousarray(z, dtype=np.float64),
               np.ascontiguousarray(zobs, dtype=np.bool_), tab.em.fused_t, tab.mu, tab.bin0, tab.bin1, tab.bin_a,
               tab.kappa, tab.kappa_global, tab.n_bins, D, W, G, GW, prow, tab.lam_rows, tab.var_q, tab.pack,
               tab.cos, tab.sin, live, live_stats, out, sd, style, phase, ll, tab.ll_feats)
    if post1 is not post:
        post[...] = post1
    state["t"] += 1
    return out, sd, _extras(style, phase)


def _extras(style: np.ndarray, phase: np.ndarray) -> list[dict]:
    """Per-stream extras of (n, C) style posteriors and (n,) phases: two conversions for the batch."""
    return [{"style": y, "phase": p} for y, p in zip(style.tolist(), phase.tolist())]


# ---- one stream, the whole step in one call -------------------------------------------------------
# A lone stream (the usual live case: one performer, a frame every 8.3 ms) pays the glue around the
# compiled code more than the code: after the daemon has waited for a frame, three compiled calls
# with their argument lists and the arrays between them cost several times the filter itself
# (docs/BENCHMARKS.md, "Run of 2026-11-23 02:40-03:30 UTC").  ``_step_slot`` runs encoder, filter and decoder
# on a state pool's row in one call, the tables packed once per model.


@_jit
def _step_slot(r, frame, observed, prev_u, prev_raw, prev_yaw, started, root_st, rt, post, t, ll, D, W, G, GW, cyc, ht,
               live, live_stats, cond, cov, prec, shrink):  # pragma: no cover - compiled
    """fastrepr.encode1 -> _step_in (-> condfill.correct1) -> fastrepr.finish1 for pool row r: the arithmetic of
    ``step`` (a batch of one) between ``fastrepr.encode`` and ``fastrepr.finish``.  Returns (completed frame,
    its std, filled mask (not observed), style posterior, phase), the arrays made here: after the daemon's
    wait each numpy call of the Python around a lone stream's step costs 10-45 us, so none is left there
    (bench/notebook/hlm9.md)."""
    center, const, dr, df, dang, any_angle, relative, rot, pos, rootf, fsrc, rsrc, normalize, mean, std, nF, root_tau, root_power = rt
    prior, d_pop, M, fused_t, mu, bin0, bin1, bin_a, kappa, kappa_g, nb, lam_rows, var_q, pack, cos, sin, lf = ht
    C = frame.shape[0]
    out = np.empty(C)
    sd = np.empty(C)
    style = np.empty(post.shape[1])
    filled = np.empty(C, np.bool_)
    for c in range(C):
        filled[c] = not observed[c]
    x = np.empty(C)
    for c in range(C):
        x[c] = frame[c] if observed[c] else np.nan
    z = np.empty(nF)
    zobs = np.empty(nF, np.bool_)
    xw = np.empty(C)
    R = np.empty((3, 3))
    encode1(x, observed, prev_u[r], prev_raw[r], prev_yaw[r], started[r], root_st[r], center, dr, df, dang, any_angle,
            relative, rot, pos, rootf, fsrc, normalize, mean, std, z, zobs, xw, R)
    q = r if cyc else 0
    zf = np.empty(nF)
    zsd = np.empty(nF)
    p = post[r].reshape(post.shape[1] * post.shape[2])
    fs, ix = scratch(p.shape[0], nF, M)
    phase, k, ll[r, 0], ll[r, 1], ll[r, 2], ll[r, 3] = _step_in(
        p, t[r] == 0, prior, d_pop, M, z, zobs, fused_t, mu, bin0, bin1, bin_a, kappa, kappa_g, nb, D[q], W[q], G[q], GW[q],
        lam_rows, var_q, pack, cos, sin, live, live_stats, zf, zsd, style, fs, ix, lf)
    t[r] += 1
    if cond:  # (on the filter's support: ix[:k])
        correct1(p, ix[:k], z, zobs, zf, M, mu, bin0, bin1, bin_a, kappa, kappa_g, D[q], W[q], G[q], GW[q], lam_rows, pack,
                 cov, prec, shrink, live, STYLE_LIVE)
    prev_yaw[r] = finish1(zf, zsd, x, observed, prev_u[r], prev_raw[r], prev_yaw[r], started[r], root_st[r], center,
                          const, dr, df, dang, relative, rot, pos, rootf, rsrc, normalize, mean, std, root_tau, root_power,
                          out, sd, z, R)  # (z: done with, finish1's working row)
    started[r] = True
    return out, sd, filled, style, phase


def slot_tables(tab, rep) -> tuple:
    """(representation tables, filter tables, zero stand-ins for the stream-cycle statistics of a
    filter without them) as ``_step_slot`` takes them."""
    t = fastrepr.tables(rep)
    rt = (t["center"], t["const"], t["dr"], t["df"], t["dang"], t["any_angle"], t["relative"], t["rot"], t["pos"],
          t["rootf"], t["fsrc"], t["rsrc"], t["normalize"], t["mean"], t["std"], int(rep.n_features), t["root_tau"],
          t["root_power"])
    ht = (tab.prior_flat, tab.d_pop, int(tab.shape[1]), tab.em.fused_t, tab.mu, tab.bin0, tab.bin1, tab.bin_a,
          float(tab.kappa), float(tab.kappa_global), int(tab.n_bins), tab.lam_rows, tab.var_q, tab.pack, tab.cos,
          tab.sin, tab.ll_feats)
    z = np.zeros((1, 1, int(rep.n_features)))
    return rt, ht, z


# The lone stream's fixed arguments (the pool's arrays, the tables, the constants) packed in one
# object, a numba structref made once per pool size: a cold call of a compiled function costs
# ~1 us an argument it unboxes and ~5 us a tuple, so the 23-argument ``_step_slot`` call costs
# ~45-50 us cold where a call with four arguments costs ~25-30 (bench/notebook/hlm9.md).  Without
# numba's structref (an older numba) step_slot calls ``_step_slot`` with its arguments as before.
SLOT_ARGS = ("prev_u", "prev_raw", "prev_yaw", "started", "root_st", "rt", "post", "t", "ll", "D", "W", "G", "GW", "cyc",
             "ht", "live", "live_stats", "cond", "cov", "prec", "shrink")
try:
    if _numba is None:
        raise ImportError("numba")
    from numba.core import types as _nbtypes
    from numba.experimental import structref as _structref

    @_structref.register
    class _SlotArgsType(_nbtypes.StructRef):
        def preprocess_fields(self, fields):
            return tuple((name, _nbtypes.unliteral(typ)) for name, typ in fields)

    class SlotArgs(_structref.StructRefProxy):
        """``_step_slot``'s arguments after the frame, in one object (``SLOT_ARGS``)."""

    _structref.define_proxy(SlotArgs, _SlotArgsType, list(SLOT_ARGS))

    @_jit
    def _slot_args(prev_u, prev_raw, prev_yaw, started, root_st, rt, post, t, ll, D, W, G, GW, cyc, ht, live, live_stats,
                   cond, cov, prec, shrink):  # pragma: no cover - compiled
        return SlotArgs(prev_u, prev_raw, prev_yaw, started, root_st, rt, post, t, ll, D, W, G, GW, cyc, ht, live,
                        live_stats, cond, cov, prec, shrink)

    @_jit
    def _step_packed(r, frame, observed, a):  # pragma: no cover - compiled
        """``_step_slot`` with its fixed arguments from ``a`` (a ``SlotArgs``)."""
        return _step_slot(r, frame, observed, a.prev_u, a.prev_raw, a.prev_yaw, a.started, a.root_st, a.rt, a.post,
                          a.t, a.ll, a.D, a.W, a.G, a.GW, a.cyc, a.ht, a.live, a.live_stats, a.cond, a.cov, a.prec, a.shrink)
except ImportError:
    _slot_args = _step_packed = None

_STEP_SLOT = _step_slot   # (step_slot packs the arguments only for this kernel, not a stand-in put in its place)


def _slot_call(tables: tuple, pool, live: float, live_stats: float, cond) -> tuple:
    """``_step_slot``'s arguments after the frame for this pool, tables and constants."""
    rt, ht, zero = tables
    rp, cp = pool.repr, pool.core
    if "D" in cp:
        D, W, G, GW, cyc = cp["D"], cp["W"], cp["G"], cp["GW"], True
    else:
        D, W, G, GW, cyc = zero, zero, zero, zero, False
    on, cov, prec, shrink = (False, zero, zero, 0.0) if cond is None else (True, cond.cov, cond.prec, cond.shrink)
    return (rp["prev_u"], rp["prev_raw"], rp["prev_yaw"], rp["started"], rp["root_st"], rt, cp["post"], cp["t"], cp["ll"], D, W,
            G, GW, cyc, ht, live, live_stats, on, cov, prec, shrink)


def step_slot(tables: tuple, pool, r: int, frame: np.ndarray, observed: np.ndarray,
              live: float = 1e-10, live_stats: float = 1e-4, cond=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """One frame of the stream in pool row r (a ``mocap.feature_model.StatePool`` of an HLM):
    frame (C,) float64, observed (C,) bool.  Updates the row in place; returns (completed (C,),
    std (C,), filled (C,) (not observed), extras).  ``tables``: ``slot_tables``'s; ``cond``: the
    model's ``condfill.CondTables`` or None (no conditional correction).  No numpy call here (the
    kernel makes the outputs) and the fixed arguments go as one packed object, made again when
    the pool grows (its arrays are new then) or anything else of them changes: a lone live
    stream runs this cold (bench/notebook/hlm9.md)."""
    pk = pool.__dict__.get("_slot_args")
    if (pk is None or pk[0] != pool.capacity or pk[1] is not tables or pk[2] is not cond or pk[3] != live
            or pk[4] != live_stats):
        args = _slot_call(tables, pool, live, live_stats, cond)
        pk = pool.__dict__["_slot_args"] = (pool.capacity, tables, cond, live, live_stats, args,
                                            None if _slot_args is None else _slot_args(*args))
    if pk[6] is not None and _step_slot is _STEP_SLOT:
        out, sd, filled, style, phase = _step_packed(r, frame, observed, pk[6])
    else:
        out, sd, filled, style, phase = _step_slot(r, frame, observed, *pk[5])
    return out, sd, filled, {"style": style.tolist(), "phase": phase}


# ---- a batch on pool rows, the whole step in one call -----------------------------------------------
# A daemon tick of n streams: encoder, filter and decoder of every stream in one compiled call on
# the pool rows themselves (no gather or scatter, contiguous or not), the working arrays made once.


@_jit
def _step_rows(prow, frames, observed, prev_u, prev_raw, prev_yaw, started, root_st, rt, post, t, ll, D, W, G, GW, cyc, ht,
               live, live_stats, out, sd, style, phase, cond, cov, prec, shrink):  # pragma: no cover - compiled
    """``_step_slot`` for pool rows prow[i] and frames[i], observed[i] (i < n), in one call:
    the same encode1 -> filter -> finish1 per stream (mirror any change to ``_step_slot``'s glue
    here), in three passes over the streams (every encoder, every filter, every decoder: each
    pass keeps its own tables in cache, which interleaving them per stream cost ~6% at 64), the
    filter's working arrays (``scratch``) shared."""
    center, const, dr, df, dang, any_angle, relative, rot, pos, rootf, fsrc, rsrc, normalize, mean, std, nF, root_tau, root_power = rt
    prior, d_pop, M, fused_t, mu, bin0, bin1, bin_a, kappa, kappa_g, nb, lam_rows, var_q, pack, cos, sin, lf = ht
    n, C = frames.shape
    CM = post.shape[1] * post.shape[2]
    x = np.empty((n, C))
    z = np.empty((n, nF))
    zobs = np.empty((n, nF), np.bool_)
    zf = np.empty((n, nF))
    zsd = np.empty((n, nF))
    xw = np.empty(C)  # (the coders' working arrays, once for the batch)
    Fv = np.empty(nF)
    R = np.empty((3, 3))
    for i in range(n):
        r = prow[i]
        for c in range(C):
            x[i, c] = frames[i, c] if observed[i, c] else np.nan
        encode1(x[i], observed[i], prev_u[r], prev_raw[r], prev_yaw[r], started[r], root_st[r], center, dr, df, dang,
                any_angle, relative, rot, pos, rootf, fsrc, normalize, mean, std, z[i], zobs[i], xw, R)
    fs, ix = scratch(CM, nF, M)
    for i in range(n):
        r = prow[i]
        q = r if cyc else 0
        p = post[r].reshape(CM)
        phase[i], k, ll[r, 0], ll[r, 1], ll[r, 2], ll[r, 3] = _step_in(
            p, t[r] == 0, prior, d_pop, M, z[i], zobs[i], fused_t, mu, bin0, bin1, bin_a, kappa, kappa_g, nb, D[q], W[q], G[q],
            GW[q], lam_rows, var_q, pack, cos, sin, live, live_stats, zf[i], zsd[i], style[i], fs, ix, lf)
        t[r] += 1
        if cond:  # (on the filter's support: ix[:k], until the next stream's _step_in)
            correct1(p, ix[:k], z[i], zobs[i], zf[i], M, mu, bin0, bin1, bin_a, kappa, kappa_g, D[q], W[q], G[q], GW[q], lam_rows,
                     pack, cov, prec, shrink, live, STYLE_LIVE)
    for i in range(n):
        r = prow[i]
        prev_yaw[r] = finish1(zf[i], zsd[i], x[i], observed[i], prev_u[r], prev_raw[r], prev_yaw[r], started[r],
                              root_st[r], center, const, dr, df, dang, relative, rot, pos, rootf, rsrc, normalize, mean,
                              std, root_tau, root_power, out[i], sd[i], Fv, R)
        started[r] = True


def step_rows(tables: tuple, pool, prow: np.ndarray, frames: np.ndarray, observed: np.ndarray,
              live: float = 1e-10, live_stats: float = 1e-4, cond=None) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """One frame of each of n streams in pool rows prow (n,) int, distinct (a
    ``mocap.feature_model.StatePool`` of an HLM): frames (n, C) float64, observed (n, C) bool.
    Updates the rows in place; returns (completed (n, C), std (n, C), extras per stream), what
    ``step_slot`` returns stream by stream.  ``tables``: ``slot_tables``'s."""
    out, sd, style, phase = step_rows_arrays(tables, pool, prow, frames, observed, live, live_stats, cond)
    return out, sd, _extras(style, phase)


def step_rows_arrays(tables: tuple, pool, prow: np.ndarray, frames: np.ndarray, observed: np.ndarray,
                     live: float = 1e-10, live_stats: float = 1e-4, cond=None, block: bool = False
                     ) -> tuple[np.ndarray, ...] | None:
    """:func:`step_rows` with the extras as the arrays the kernel writes them in: (completed
    (n, C), std (n, C), style posteriors (n, K), phases (n,)), no dict per stream.  ``block``
    (``HLMModel.step_block``'s call): also check that no row is given twice (None, nothing
    changed, if one is) and return the filled mask (n, C) (not observed) fifth.  The rows' checks and
    the output arrays are the compiled call's (``_block_rows``), and the inputs are converted
    only where they need it: a live tick runs this glue cold, where each numpy call costs
    microseconds (bench/notebook/hlm64-7.md)."""
    rt, ht, zero = tables
    rp, cp = pool.repr, pool.core
    n, C = frames.shape
    if type(prow) is not np.ndarray or prow.dtype != _I64:
        prow = np.asarray(prow, dtype=np.int64)
    if prow.shape != (n,):
        raise IndexError(f"pool rows {prow.tolist()} for {n} frames in a pool of {pool.capacity}")
    if not (frames.dtype == _F64 and frames.flags.c_contiguous):
        frames = np.ascontiguousarray(frames, dtype=np.float64)
    if not (observed.dtype == _BOOL and observed.flags.c_contiguous):
        observed = np.ascontiguousarray(observed, dtype=np.bool_)
    if not (frames.flags.writeable and observed.flags.writeable):  # (compiled for writable arrays: no second kernel)
        frames, observed = frames.copy(), observed.copy()
    if "D" in cp:
        code, out, sd, style, phase, filled = _block_rows(
            prow, frames, observed, rp["prev_u"], rp["prev_raw"], rp["prev_yaw"], rp["started"], rp["root_st"], rt,
            cp["post"], cp["t"], cp["ll"], cp["D"], cp["W"], cp["G"], cp["GW"], True, ht, live, live_stats,
            *((False, zero, zero, 0.0) if cond is None else (True, cond.cov, cond.prec, cond.shrink)), block)
    else:
        code, out, sd, style, phase, filled = _block_rows(
            prow, frames, observed, rp["prev_u"], rp["prev_raw"], rp["prev_yaw"], rp["started"], rp["root_st"], rt,
            cp["post"], cp["t"], cp["ll"], zero, zero, zero, zero, False, ht, live, live_stats,
            *((False, zero, zero, 0.0) if cond is None else (True, cond.cov, cond.prec, cond.shrink)), block)
    if code == 1:  # (compiled code has no bounds checks)
        raise IndexError(f"pool rows {prow.tolist()} for {n} frames in a pool of {pool.capacity}")
    if code:
        return None
    return (out, sd, style, phase, filled) if block else (out, sd, style, phase)


@_jit
def _block_rows(prow, frames, observed, prev_u, prev_raw, prev_yaw, started, root_st, rt, post, t, ll, D, W, G, GW, cyc, ht,
                live, live_stats, cond, cov, prec, shrink, block):  # pragma: no cover - compiled
    """``_step_rows`` on pool rows prow after checking them, with its output arrays made here:
    returns (code, completed, std, style posteriors, phases, filled); code 0: stepped; 1: a row
    outside the pool; 2 (only if ``block``): a row given twice, or outside the pool (the caller's
    slower path tells which first, as it checks); nothing is changed then.  ``filled``: with
    ``block``, not observed (the block's filled mask, which a numpy call would cost a cold tick
    tens of microseconds for), else empty."""
    n, C = frames.shape
    cap = post.shape[0]
    out = np.empty((n, C))
    sd = np.empty((n, C))
    style = np.empty((n, post.shape[1]))
    phase = np.empty(n)
    filled = np.empty((n if block else 0, C), np.bool_)
    for i in range(n):
        if prow[i] < 0 or prow[i] >= cap:
            return 2 if block else 1, out, sd, style, phase, filled
    if block:
        seen = np.zeros(cap, np.bool_)
        for i in range(n):
            if seen[prow[i]]:
                return 2, out, sd, style, phase, filled
            seen[prow[i]] = True
        for i in range(n):
            for c in range(C):
                filled[i, c] = not observed[i, c]
    _step_rows(prow, frames, observed, prev_u, prev_raw, prev_yaw, started, root_st, rt, post, t, ll, D, W, G, GW, cyc, ht,
               live, live_stats, out, sd, style, phase, cond, cov, prec, shrink)
    return 0, out, sd, style, phase, filled
