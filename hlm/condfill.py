"""The missing features given the observed ones within the stream's own cycle: a conditional
Gaussian correction of the online fill (an extension beyond the paper; off in the faithful
methods and in model files written before it).

The HLM's emission is diagonal within a state (eq. 10): given the phase, a missing arm learns
nothing from the other arm, the spine or the root.  But how a performer deviates from their own
cycle at this moment (leaning into a turn, a longer stride, a wider swing) shows in every limb at
once.  Let r = x - x_hat be the residual of a frame about the eq. (18) fill x_hat computed for
every feature from the joint posterior and the stream's own cycle (mu + delta, ``hlm.streamcycle``).
Residuals of the training takes, filtered online with everything observed, give a covariance per
style, Sigma_c (F x F, with a ridge), each frame's residual weighed by the filter's posterior of
the style (basketball's arms do not teach a walker's); the root's features are made independent of the body's in it (their
cross-covariance set to 0), so the root stays as ``mocap.representation`` integrates and damps
it: a correction of the root's velocities would add up over a root gap (on VALIDATION it turned
the heading of turns 85 -> 100 deg RMS with the root erased, and left the body's gain as it was).
Over a gap the missing features get

    x_m = x_hat_m + s sum_c P(c) Sigma^c_mo (Sigma^c_oo)^-1 r_o

the mean of the missing residual given the observed one under the styles' N(0, Sigma_c) (styles
above STYLE_LIVE of the most probable, renormalised), shrunk by s
(``cond_shrink``, chosen on VALIDATION: bench/notebook/hlmq-4.md; in-sample residuals of the
training takes understate how a new performer's differ).  The same mean is -Q_mm^-1 Q_mo r_o with
Q = Sigma^-1 (the Schur complement identity); the smaller of the two systems is solved (a limb
gap solves a few missing features, pan2009's all-but-legs the 14 observed).  The reported std is
left as the filter's (an upper bound: conditioning only lowers the variance).

``correct`` (numpy) is the reference; ``correct_many`` (numba) is the same arithmetic, stream by
stream, for the compiled step (``hlm.fast``); ``tests/test_hlm_model_cond.py`` checks them equal.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lacuna.jit import jit as _jit

RIDGE = 0.1      # added to Sigma's diagonal (feature units squared: degrees^2 for angles)
LIVE = 1e-10     # states below this fraction of the largest posterior are skipped (as hlm.online.fill)
STYLE_LIVE = 1e-3  # styles below this fraction of the most probable one add no correction
PRIOR_FRAMES = 1000.0  # pseudo-frames of the pooled covariance in each style's (cov_from_sums)


def _jit_numpy_errors(fn):
    """``jit`` with numba's numpy error model: a float division by zero gives inf/nan as numpy's does
    instead of a test and a ZeroDivisionError before each division (``correct1``: its divisors are
    positive, and the test keeps its division loops out of SIMD lanes)."""
    return _jit(fn, error_model="numpy")


class CondTables:
    """Sigma_c (C, F, F), their inverses Q_c and the shrink s, as the kernels take them."""

    def __init__(self, cov: np.ndarray, shrink: float):
        self.cov = np.ascontiguousarray(cov, dtype=np.float64)
        self.prec = np.ascontiguousarray(np.linalg.inv(self.cov))
        self.shrink = float(shrink)


def fit_cov(tab, feats: Sequence[np.ndarray], root: np.ndarray | None = None,
            prior_frames: float = PRIOR_FRAMES) -> np.ndarray:
    """Sigma_c from training feature sequences [(n_k, F)], everything observed: the online filter
    (numpy reference path, ``hlm.online``) runs over each, and r_t = z_t - x_hat_t is taken
    after each frame's update, weighed by the style posterior.  root (F,) bool: the root's
    features, made independent of the others (module doc).  Returns Sigma_c + RIDGE I (C, F, F)."""
    return cov_from_sums(*residual_sums(tab, feats), root, prior_frames)


def residual_sums(tab, feats: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(sum_t P_t(c) r_t r_t^T (C, F, F), sum_t P_t(c) (C,)) over the training sequences."""
    from hlm import online

    F = tab.mu.shape[1]
    C = tab.shape[0]
    S = np.zeros((C, F, F))
    n = np.zeros(C)
    for z in feats:
        z = np.asarray(z, dtype=np.float64)
        st = online.init_state(tab, 1)
        for t in range(z.shape[0]):
            o = np.isfinite(z[t : t + 1])
            online.update(tab, st, z[t : t + 1], o, want_ll=False)
            online.accumulate(tab, st, z[t : t + 1], o)
            r = z[t] - expected(tab, st, 0)
            if np.isfinite(r).all():
                pc = st["post"][0].sum(1)
                S += pc[:, None, None] * np.outer(r, r)[None]
                n += pc
    return S, n


def cov_from_sums(S: np.ndarray, n: np.ndarray, root: np.ndarray | None = None,
                  prior_frames: float = PRIOR_FRAMES) -> np.ndarray:
    """Sigma_c = (S_c + n0 Sigma_pooled) / (n_c + n0): each style's covariance shrunk toward all
    styles' by n0 = prior_frames pseudo-frames (a style seen in few frames borrows the rest's
    correlations; n0 = inf is one pooled covariance), the root apart, plus RIDGE I."""
    pooled = S.sum(0) / max(n.sum(), 1e-12)
    if np.isinf(prior_frames):
        out = np.repeat(pooled[None], S.shape[0], 0)
    else:
        out = (S + prior_frames * pooled[None]) / (n + prior_frames + 1e-12)[:, None, None]
    if root is not None:
        root = np.asarray(root, dtype=bool)
        out[:, root[:, None] & ~root[None, :]] = 0.0
        out[:, ~root[:, None] & root[None, :]] = 0.0
    return out + RIDGE * np.eye(S.shape[1])[None]


def expected(tab, state: dict[str, np.ndarray], i: int, r: int | None = None) -> np.ndarray:
    """x_hat (F,) of stream i for every feature: eq. (18) over the live states on the stream's
    own cycle (``hlm.online.fill`` with nothing observed); r: its row of the cycle statistics."""
    from hlm import online

    z = np.zeros((1, tab.mu.shape[1]))
    P = state["post"][i : i + 1]
    D, W = online.cycle_stats(state)
    G = online.group_stats(state)
    row = i if r is None else r
    if D is not None:
        D, W = D[row : row + 1], W[row : row + 1]
        G = {k: v[row : row + 1] for k, v in G.items()}
    out, _ = online.fill(tab, P, z, np.zeros(z.shape, bool), D, W, **G)
    return out[0]


def conditional(ct: CondTables, c: int, r_o: np.ndarray, o: np.ndarray, m: np.ndarray) -> np.ndarray:
    """E[r_m | r_o] under style c's N(0, Sigma_c), solving the smaller system (module doc)."""
    if m.sum() <= o.sum():
        Q = ct.prec[c]
        return -np.linalg.solve(Q[np.ix_(m, m)], Q[np.ix_(m, o)] @ r_o)
    S = ct.cov[c]
    return S[np.ix_(m, o)] @ np.linalg.solve(S[np.ix_(o, o)], r_o)


def style_weights(post: np.ndarray) -> np.ndarray:
    """(C,) the styles' posterior above STYLE_LIVE of the largest, renormalised (0 below)."""
    pc = post.sum(-1)
    pc = np.where(pc > STYLE_LIVE * pc.max(), pc, 0.0)
    return pc / pc.sum()


def correct(tab, ct: CondTables, state: dict[str, np.ndarray], z: np.ndarray, zobs: np.ndarray, zf: np.ndarray,
            rows: np.ndarray | None = None) -> None:
    """Add the conditional correction to the fills zf (n, F) in place (numpy reference): each
    stream with something missing and something observed."""
    for i in range(z.shape[0]):
        o = zobs[i]
        m = ~o
        if not o.any() or not m.any():
            continue
        xh = expected(tab, state, i, None if rows is None else int(rows[i]))
        w = style_weights(state["post"][i])
        corr = np.zeros(int(m.sum()))
        for c in np.flatnonzero(w):
            corr += w[c] * conditional(ct, int(c), z[i, o] - xh[o], o, m)
        zf[i, m] += ct.shrink * corr


@_jit
def _chol_solve_in(A, b, L, y, x):  # pragma: no cover - compiled
    """x with A x = b for symmetric positive definite A (n, n) (Cholesky, then two triangular solves),
    into the caller's arrays L (n, n), y, x (n,) (``correct1``'s one block; the
    same operations in the same order, so the same bits): returns x."""
    n = A.shape[0]
    for j in range(n):
        for k in range(n):
            L[j, k] = 0.0
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        L[j, j] = np.sqrt(s)
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / L[j, j]
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = y[i]
        for k in range(i + 1, n):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]
    return x


@_jit_numpy_errors
def correct1(post, sup, z, zobs, zf, M, mu, bin0, bin1, bin_a, kappa, kappa_g, D, W, G, GW, lam_rows, pack,
             cov, prec, shrink, live, style_live):  # pragma: no cover - compiled
    """``correct`` for one stream: post (C M,) its filtered posterior, D, W, G, GW its cycle
    statistics (ignored when kappa = 0), zf (F,) its fill, corrected in place.

    sup: the states to visit, ascending, with post exactly 0 at every state not in it (the
    filter's support, ``hlm.fast._step_in``'s rows; ``np.arange(C M)`` visits all).  The result
    is the bits of a pass over all C*M states: each sum below runs over the same states in the
    same ascending order, and a state left out adds nothing -- its post is +-0, which no
    ``post > live * pmax`` test lets into ptot or x_hat (live * pmax >= 0), which cannot raise
    pmax (posts are >= 0), and which added to a style's pc (starting at +0.0, never -0.0) leaves
    it as it was.

    Each quantity is computed by the same operations in the same order as before (so the same
    bits), laid out for the machine: a live knot's offsets E and a live state's x_hat terms for
    every feature in contiguous rows (SIMD lanes: IEEE division, products and sums lane by lane
    are the scalar ones; the missing features' entries are computed and not used), each
    right-hand side's sums in registers, four rows at a time (each row's terms still added in
    ascending feature order).  Compiled with numpy's error model (no zero test before each
    division: what keeps the division loops out of SIMD); every divisor here is positive
    (kappa + W, kappa_g + GW, x_hat's sum of p lambda, ptot, the styles' sum, a Cholesky pivot
    of a Sigma or Q with RIDGE on its diagonal)."""
    F = z.shape[0]
    no = 0
    for f in range(F):
        if zobs[f]:
            no += 1
    nm = F - no
    if no == 0 or nm == 0:
        return
    CM = post.shape[0]
    ns = sup.shape[0]
    C = CM // M
    CB = D.shape[0] if kappa > 0.0 else 1
    n2 = min(nm, no)  # (the smaller system is solved: its matrix, factor and vectors are n2 long)
    # the working arrays in two blocks (an allocation costs more than the arithmetic on them), the
    # knots' offsets E last: a cold tick pays for every line it touches, and few of E's rows are
    ws = np.empty(3 * F + C + nm + 2 * n2 * n2 + 2 * n2 + nm + CB * F)
    iw = np.empty(F + CB, np.int64)
    oi = iw[:no]
    mi = iw[no:F]
    done = iw[F:]
    a_ = 0
    b_ = 0
    for f in range(F):
        if zobs[f]:
            oi[a_] = f
            a_ += 1
        else:
            mi[b_] = f
            b_ += 1
    # x_hat at the observed features (the arithmetic of hlm.online.fill / hlm.fast._step_in's fill)
    pmax = 0.0
    for i in range(ns):
        if post[sup[i]] > pmax:
            pmax = post[sup[i]]
    ptot = 0.0
    for i in range(ns):
        if post[sup[i]] > live * pmax:
            ptot += post[sup[i]]
    num = ws[:F]
    den = ws[F : 2 * F]
    r = ws[2 * F : 2 * F + no]
    pc = ws[3 * F : 3 * F + C]
    o = 3 * F + C
    corr = ws[o : o + nm]
    o += nm
    Aw = ws[o : o + n2 * n2]
    o += n2 * n2
    Lw = ws[o : o + n2 * n2]
    o += n2 * n2
    yw = ws[o : o + n2]
    xw = ws[o + n2 : o + 2 * n2]
    o += 2 * n2
    bw = ws[o : o + nm]
    o += nm
    E = ws[o : o + CB * F].reshape((CB, F))
    for f in range(F):
        num[f] = 0.0
        den[f] = 0.0
    # the knot offsets, each live knot's row computed once (live states share a few)
    nbk = max(CB // C, 1)
    for b in range(CB):
        done[b] = 0
    for i in range(ns):
        s = sup[i]
        p = post[s]
        if not p > live * pmax:
            continue
        p /= ptot
        if kappa > 0.0:
            b0, b1, a = bin0[s], bin1[s], bin_a[s]
            for b in (b0, b1):
                if done[b] == 0:
                    done[b] = 1
                    cb = b // nbk
                    if kappa_g > 0.0:
                        for f in range(F):
                            g = G[cb, f] / (kappa_g + GW[cb, f])
                            E[b, f] = g + (D[b, f] - W[b, f] * g) / (kappa + W[b, f])
                    else:
                        for f in range(F):
                            E[b, f] = D[b, f] / (kappa + W[b, f])
            for f in range(F):
                u = mu[s, f] + (1.0 - a) * E[b0, f] + a * E[b1, f]
                lam = lam_rows[s, f]
                num[f] += p * lam * u
                den[f] += p * lam
        else:
            for f in range(F):
                num[f] += p * pack[s, f]
                den[f] += p * pack[s, F + f]
    for j in range(no):
        f = oi[j]
        r[j] = z[f] - num[f] / den[f]
    # the styles' weights (style_weights)
    for c in range(C):
        pc[c] = 0.0
    c = 0
    top = M
    for i in range(ns):  # pc[s // M] += post[s] for ascending s: the same sums, no division a state
        s = sup[i]
        while s >= top:
            c += 1
            top += M
        pc[c] += post[s]
    cmax = 0.0
    for c in range(C):
        if pc[c] > cmax:
            cmax = pc[c]
    csum = 0.0
    for c in range(C):
        if pc[c] > style_live * cmax:
            csum += pc[c]
        else:
            pc[c] = 0.0
    for i in range(nm):
        corr[i] = 0.0
    for c in range(C):
        if pc[c] == 0.0:
            continue
        wc = pc[c] / csum
        if nm <= no:
            # -Q_mm^-1 Q_mo r_o
            A = Aw[: nm * nm].reshape((nm, nm))
            b = bw[:nm]
            for i in range(nm):
                for j in range(nm):
                    A[i, j] = prec[c, mi[i], mi[j]]
            _rows_dot(prec, c, mi, oi, r, b)
            x = _chol_solve_in(A, b, Lw[: nm * nm].reshape((nm, nm)), yw[:nm], xw[:nm])
            for i in range(nm):
                corr[i] -= wc * x[i]
        else:
            # Sigma_mo Sigma_oo^-1 r_o
            A = Aw[: no * no].reshape((no, no))
            for i in range(no):
                for j in range(no):
                    A[i, j] = cov[c, oi[i], oi[j]]
            y = _chol_solve_in(A, r, Lw[: no * no].reshape((no, no)), yw[:no], xw[:no])
            b = bw[:nm]
            _rows_dot(cov, c, mi, oi, y, b)
            for i in range(nm):
                corr[i] += wc * b[i]
    for i in range(nm):
        zf[mi[i]] += shrink * corr[i]


@_jit
def _rows_dot(S, c, ri, ci, v, out):  # pragma: no cover - compiled
    """out[i] = sum_j S[c, ri[i], ci[j]] v[j], each sum from 0.0 in ascending j (the bits of the loop
    written so), four rows at a time in registers (four independent chains of additions, where one
    row alone waits on each addition's latency).  (Indexed in place, no row views: each view of an
    array costs numba a reference count up and down, atomic operations.)"""
    n = ri.shape[0]
    m = ci.shape[0]
    i = 0
    while i + 4 <= n:
        r0, r1, r2, r3 = ri[i], ri[i + 1], ri[i + 2], ri[i + 3]
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        a3 = 0.0
        for j in range(m):
            f = ci[j]
            vj = v[j]
            a0 += S[c, r0, f] * vj
            a1 += S[c, r1, f] * vj
            a2 += S[c, r2, f] * vj
            a3 += S[c, r3, f] * vj
        out[i] = a0
        out[i + 1] = a1
        out[i + 2] = a2
        out[i + 3] = a3
        i += 4
    while i < n:
        r0 = ri[i]
        acc = 0.0
        for j in range(m):
            acc += S[c, r0, ci[j]] * v[j]
        out[i] = acc
        i += 1


@_jit
def _correct_many(post, z, zobs, zf, prow, M, mu, bin0, bin1, bin_a, kappa, kappa_g, D, W, G, GW, lam_rows, pack,
                  cov, prec, shrink, live, style_live):  # pragma: no cover - compiled
    sup = np.empty(post.shape[1], np.int64)
    for i in range(post.shape[0]):
        r = prow[i]
        k = 0
        for s in range(post.shape[1]):  # (the states with post != 0: correct1's support)
            if post[i, s] != 0.0:
                sup[k] = s
                k += 1
        correct1(post[i], sup[:k], z[i], zobs[i], zf[i], M, mu, bin0, bin1, bin_a, kappa, kappa_g, D[r], W[r], G[r], GW[r],
                 lam_rows, pack, cov, prec, shrink, live, style_live)


def correct_many(tab, ct: CondTables, state: dict[str, np.ndarray], z: np.ndarray, zobs: np.ndarray, zf: np.ndarray,
                 rows: np.ndarray | None = None) -> None:
    """``correct`` compiled: the same arguments, zf (n, F) corrected in place."""
    n, F = z.shape
    post = np.ascontiguousarray(state["post"].reshape(n, -1))
    if tab.kappa > 0.0:
        D, W, G, GW = state["D"], state["W"], state["G"], state["GW"]
        prow = np.arange(n, dtype=np.int64) if rows is None else np.asarray(rows, dtype=np.int64)
    else:
        D = W = G = GW = np.zeros((1, 1, F))
        prow = np.zeros(n, dtype=np.int64)
    _correct_many(post, np.ascontiguousarray(z, dtype=np.float64), np.ascontiguousarray(zobs, dtype=np.bool_), zf,
                  prow, int(tab.shape[1]), tab.mu, tab.bin0, tab.bin1, tab.bin_a, float(tab.kappa),
                  float(tab.kappa_global), D, W, G, GW, tab.lam_rows, tab.pack, ct.cov, ct.prec, ct.shrink, LIVE,
                  STYLE_LIVE)
