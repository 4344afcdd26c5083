"""The stream-cycle adaptation of the online HLM filter: per-stream statistics and offsets.

Stream cycle adaptation (``kappa > 0``; an extension beyond the paper, off in the faithful
configuration): the stream gets its own latent cycle, its style's cycle plus a slowly varying
offset, z^{s,c}_m = mu^c_m + delta^c(m), with delta piecewise linear over ``n_bins`` knots around
the cycle (knots 2 ``width`` + 1 states apart) and a Gaussian prior N(0, 1/(kappa lambda^c_f)) on
each knot.  Every observed frame adds its residual x - mu^c_m, weighted by the filtered posterior
and split between the two neighbouring knots, to D and its weight to W; the knot's posterior mean
is D / (kappa + W).  A performer whose arms swing wider than the training population's, or whose
neck is held higher, is filled with their own motion once a cycle of it has been seen.  Only the
live states of the posterior are touched (sparse), so a frame costs O(k F); the per-stream state
is 2 C n_bins F numbers (about 60 kB at C = 4, M = 280, width 8).  With ``kappa_global > 0`` the
offset has a second level, a constant per style under the knots (see ``stream_offset``), so the
phases not yet seen move with the rest.  The emission keeps the style cycle (alignment stays
that of the trained model), except with a change of style (``hlm.online``), where it is weighed
on the stream's own cycle (``adapted_loglik``).  The reported std does not yet include the
uncertainty of the offset estimate itself (about 1 / sqrt(lambda (kappa + W)) per knot).

Every function here works batched over streams; the statistics D, W (n, C n_bins, F) and their
per-style sums G, GW (n, C, F) live in the stream state (``hlm.online.init_state``), in a model's
state pool when served through ``mocap.feature_model`` (then indexed by the pool rows ``prow``).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from hlm.tables import FilterTables

LIVE_STATS = 1e-4  # stream-cycle statistics: contributions below this fraction are skipped


def group_stats(state: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The per-style sums G, GW of a state, as keywords of ``fill`` (empty without adaptation)."""
    return {"G": state["G"], "GW": state["GW"]} if "G" in state else {}


def cycle_stats(state: dict[str, np.ndarray]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The knot statistics D, W of a state (None, None without adaptation)."""
    return state.get("D"), state.get("W")


def _runs(s: np.ndarray) -> np.ndarray:
    """Start of each run of equal values in s (K,), which is grouped (as np.nonzero returns)."""
    return np.flatnonzero(np.concatenate(([True], s[1:] != s[:-1])))


def _live(P: np.ndarray, sel: np.ndarray, frac: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The live (stream, state) pairs of the streams ``sel``: states above ``frac`` of their stream's
    largest posterior.  Returns (stream index into the batch, flat state, posterior), each (K,),
    grouped by stream with states ascending (row-major), so per-stream sums are contiguous runs."""
    Pf = P.reshape(P.shape[0], -1)[sel]
    si, rows = np.nonzero(Pf > frac * Pf.max(1, keepdims=True))
    return sel[si], rows, Pf[si, rows]


def accumulate(tab: FilterTables, state: dict[str, np.ndarray], z: np.ndarray, zobs: np.ndarray,
               P: np.ndarray | None = None, prow: np.ndarray | None = None) -> None:
    """Add this frame's residuals to the stream-cycle statistics D, W (only when ``kappa > 0``).

    prow (n,): when given, D and W are a state pool's (capacity, C n_bins, F) arrays and stream i
    of the batch owns their row prow[i] (``mocap.feature_model``); else they are the batch's own.

    Vectorised over the batch: the live (stream, state) pairs of every stream that observed
    something are scattered at once into the (n, C n_bins, F) statistics.  Each knot belongs to
    one stream, so this equals a stream-by-stream loop up to the order of the additions (tested
    to 1e-9 against that loop)."""
    if tab.kappa <= 0.0:
        return
    P = state["post"] if P is None else P
    sel = np.flatnonzero(zobs.any(1))
    if sel.size == 0:
        return
    D, W = state["D"], state["W"]
    if sel.size == 1:
        # a lone stream: the direct path costs fewer numpy calls than the batched gather
        i = sel[0]
        Pf = P[i].reshape(-1)
        rows = np.flatnonzero(Pf > LIVE_STATS * Pf.max())
        p = Pf[rows]
        o = zobs[i].astype(np.float64)
        dev = o * (np.where(zobs[i], z[i], 0.0) - tab.mu[rows])                  # (k, F)
        r = i if prow is None else prow[i]
        B = tab.knot_weights[rows] * p[:, None]        # (k, C n_bins): each state's share of its two knots
        dD, dW = B.T @ dev, B.sum(0)
        D[r] += dD
        W[r] += dW[:, None] * o
        if "G" in state:
            C = tab.em.C
            state["G"][r] += dD.reshape(C, -1, dD.shape[1]).sum(1)
            state["GW"][r] += dW.reshape(C, -1).sum(1)[:, None] * o
        return
    s, rows, p = _live(P, sel, LIVE_STATS)
    a = tab.bin_a[rows]
    ob = zobs[s]
    o = ob.astype(np.float64)                                                    # (K, F)
    dev = o * (np.where(ob, z[s], 0.0) - tab.mu[rows])
    cb = tab.em.C * tab.n_bins
    # the pairs come grouped by stream with states ascending, so the pairs sending a term to one
    # knot form one contiguous run (for bin1 too: only a style's last states wrap to its knot 0)
    # and a reduceat over the runs sums each knot's terms; each touched knot is then added once
    for bins, w in ((tab.bin0[rows], p * (1.0 - a)), (tab.bin1[rows], p * a)):
        dest = s * cb + bins
        first = _runs(dest)
        ks, kb = s[first], bins[first]          # distinct runs are distinct knots: += never collides
        if prow is not None:
            ks = prow[ks]
        D[ks, kb] += np.add.reduceat(w[:, None] * dev, first)
        W[ks, kb] += np.add.reduceat(w, first)[:, None] * o[first]
    if "G" in state:
        # per (stream, style): a state's two knot weights sum to its posterior p
        c = tab.style_of[rows]
        first = _runs(s * tab.em.C + c)
        ks = s[first] if prow is None else prow[s[first]]
        state["G"][ks, c[first]] += np.add.reduceat(p[:, None] * dev, first)
        state["GW"][ks, c[first]] += np.add.reduceat(p, first)[:, None] * o[first]


def stream_offset(tab: FilterTables, rows: np.ndarray, D: np.ndarray, W: np.ndarray) -> np.ndarray:
    """delta(m) at the given flat states (k, F) from one stream's knot statistics D, W (C nb, F).

    With ``kappa_global > 0`` the offset is two-level: a constant per style g_c (all the stream's
    residuals, prior pseudo-count kappa_global) plus knot deviations from it, so phases the stream
    has not shown yet still move by the offset seen elsewhere in the cycle."""
    k = tab.kappa
    b0, b1, a = tab.bin0[rows], tab.bin1[rows], tab.bin_a[rows, None]
    if tab.kappa_global <= 0.0:
        return (1.0 - a) * D[b0] / (k + W[b0]) + a * D[b1] / (k + W[b1])
    nb = tab.n_bins
    c = tab.style_of[rows]
    Dg = D.reshape(-1, nb, D.shape[1]).sum(1)                   # (C, F): knot weights sum to 1 per frame
    Wg = W.reshape(-1, nb, W.shape[1]).sum(1)
    g = (Dg / (tab.kappa_global + Wg))[c]                        # (k, F)
    return g + (1.0 - a) * (D[b0] - W[b0] * g) / (k + W[b0]) + a * (D[b1] - W[b1] * g) / (k + W[b1])


def knot_offsets(tab: FilterTables, D: np.ndarray, W: np.ndarray, G: np.ndarray | None = None,
                 GW: np.ndarray | None = None) -> np.ndarray:
    """The offset at every knot of one stream (C nb, F), so that ``stream_offset`` at states rows
    is ``tab.knot_weights[rows] @ knot_offsets(...)`` (the knot weights of a state sum to 1, so the
    per-style constant g moves inside the knots).  Cheaper for a lone stream: whole (C nb, F)
    arrays in a few calls instead of gathers per state."""
    if tab.kappa_global <= 0.0:
        return D / (tab.kappa + W)
    nb, F = tab.n_bins, D.shape[1]
    D3, W3 = D.reshape(-1, nb, F), W.reshape(-1, nb, F)
    if G is None:
        G, GW = D3.sum(1), W3.sum(1)
    g = (G / (tab.kappa_global + GW))[:, None, :]                     # (C, 1, F)
    return (g + (D3 - W3 * g) / (tab.kappa + W3)).reshape(D.shape)


def pair_offsets(tab: FilterTables, R: np.ndarray, W: np.ndarray, ps: np.ndarray, rows: np.ndarray,
                 G: np.ndarray | None = None, GW: np.ndarray | None = None) -> np.ndarray:
    """The stream offset delta at K (stream, state) pairs (K, F), batched: ps (K,) the streams'
    rows of R, W (n, C n_bins, F); rows (K,) flat states.  Only the knots next to the pairs'
    states are read (a few per stream, of C n_bins).  Equals ``stream_offset`` pair by pair."""
    n, cb, F = R.shape
    nb = tab.n_bins
    K = rows.size
    u, inv = np.unique(np.concatenate([ps * cb + tab.bin0[rows], ps * cb + tab.bin1[rows]]), return_inverse=True)
    Du, Wu = R.reshape(-1, F)[u], W.reshape(-1, F)[u]
    a = tab.bin_a[rows, None]
    if tab.kappa_global <= 0.0:
        Eu = Du / (tab.kappa + Wu)
        return (1.0 - a) * Eu[inv[:K]] + a * Eu[inv[K:]]
    # the per-style constant g (stream_offset) at each knot's (stream, style)
    if G is not None:
        sc = u // nb                                          # flat (stream, style) ids
        gu = G.reshape(-1, F)[sc] / (tab.kappa_global + GW.reshape(-1, F)[sc])
    else:
        sc, sinv = np.unique(u // nb, return_inverse=True)
        Dg = R.reshape(n * (cb // nb), nb, F)[sc].sum(1)
        Wg = W.reshape(n * (cb // nb), nb, F)[sc].sum(1)
        gu = (Dg / (tab.kappa_global + Wg))[sinv]
    Eu = (Du - Wu * gu) / (tab.kappa + Wu)
    return gu[inv[:K]] + ((1.0 - a) * Eu[inv[:K]] + a * Eu[inv[K:]])


def adapted_loglik(tab: FilterTables, x: np.ndarray, o: np.ndarray, rows: np.ndarray, off: np.ndarray) -> np.ndarray:
    """ell of K states on the stream's own cycle mu + delta (the emission of ``hlm.emissions`` with
    the adapted mean): x, o (K, F) each pair's frame (0 where missing) and mask; off (K, F)."""
    F = x.shape[-1]
    t = tab.emit_pack[rows]                     # [mu | lam / 2 | emit_a] in one gather
    r = x - t[:, :F] - off
    return ((t[:, 2 * F :] - t[:, F : 2 * F] * r * r) * o).sum(1)
