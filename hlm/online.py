"""The online forward filter of the HLM over the joint (style, phase) state, batched over streams.

Per frame (O(C M J + C M F), independent of how long the stream has run):

  predict   p(c, m | x_<t) = sum_j d_j p(c, m - j | x_<t)        eq. (1); the first frame uses
            tau_c / M (the style prior and the uniform start of step 4c)
  update    p(c, m | x_<=t) ~ p(c, m | x_<t) exp(ell_t(c, m))   ell over the observed features only
  fill      eq. (18) with the joint posterior: x_dag = (sum_c P(c) Lambda^c)^-1 sum_cm P(c,m) Lambda^c mu^{c,m}
  std       sqrt of the predictive mixture second moment about the fill: within-state 1/lambda,
            Q(Z) variance, and the spread of the state means (between-state) plus the offset of the
            precision-weighted fill from the mixture mean
  extras    style posterior P(c) and phase = circular mean of m / M under P(m)

The posterior is kept as probabilities normalised every frame, the emission enters as
exp(ell - max ell) so nothing underflows as a whole; this is the normalised log-space forward
recursion of ``hlm.hmm.forward`` (tested equal).  A frame that never arrives (nothing observed)
is a pure prediction step.  The emission is evaluated only on the prediction's support (the
states with nonzero predicted probability, a few dozen of C M once the phase is known), which
is exact: the posterior is zero elsewhere whatever the emission.

Stream cycle adaptation (``kappa > 0``; an extension beyond the paper, off in the faithful
configuration): the stream's own cycle is its style's cycle plus a learned offset; see
``hlm.streamcycle``.

Change of style (``style_switch = h > 0``; an extension, off by default and in the faithful
configuration, where each recording has one style): after the prediction, mass h of every state
holding more than SWITCH_LIVE of the largest moves to the other styles at the same phase (the
style cycles are children of one parent cycle, eq. 5, so phase m is the same point of the gait
in each), and posteriors below PRUNE of the largest are dropped, which keeps the support small.
A performer who walks and then runs is followed within a frame or two; without it a style whose
posterior has underflowed never returns.  With both the switch and the stream-cycle adaptation,
the emission is weighed on the stream's own cycle mu + delta (``_adapted``).

Transition adaptation (``adapt_rate > 0``): each frame adds the filtered expected jump
probabilities P(jump = j | x_<=t) to exponentially forgotten counts n_j <- (1 - rate) n_j + xi_j,
and d = (prior_strength d_pop + n) / (prior_strength + sum n).  A performer who walks faster
than the training population moves probability to longer jumps within a second or two; with
``adapt_rate = 0`` d stays at the population value d_pop (the mean of the training d^k).
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import correlate1d

from hlm.streamcycle import (  # noqa: F401
    LIVE_STATS,
    _live,
    _runs,
    accumulate,
    adapted_loglik,
    cycle_stats,
    group_stats,
    knot_offsets,
    pair_offsets,
    stream_offset,
)
from hlm.tables import FilterTables


def init_state(tab: FilterTables, n: int) -> dict[str, np.ndarray]:
    C, M = tab.shape
    J = tab.d_pop.shape[0]
    st = {
        "post": np.zeros((n, C, M)),          # filtered p(c, m | x_<=t); unused before frame 0
        "t": np.zeros(n, dtype=np.int64),     # frames consumed
        "d": np.tile(tab.d_pop, (n, 1)),      # current transition probabilities
        "counts": np.zeros((n, J)),           # forgotten expected jump counts (adaptation)
        # the last frame's one-step predictive log-likelihood of the observed features, log p(z_t,o | z_<t,o)
        # (the forward step's normaliser, the emission's constants kept), and how many features were observed
        # (0: a pure prediction step); read by default's long-erasure evidence (blend/withhlm.py, "long_ll");
        # columns 2-3 the same over the observed features of tab.ll_feats only (the legs, where default asks:
        # the emission is diagonal, so a partial sum of the same terms on the same support; 0, 0 where none)
        "ll": np.zeros((n, 4)),
    }
    if tab.kappa > 0.0:
        F = tab.mu.shape[1]
        st["D"] = np.zeros((n, C * tab.n_bins, F))   # stream-cycle residual sums (see module doc)
        st["W"] = np.zeros((n, C * tab.n_bins, F))   # and their weights
        st["G"] = np.zeros((n, C, F))                # D and W summed over each style's knots
        st["GW"] = np.zeros((n, C, F))               # (kept up to date, for the per-style constant)
    return st


LIVE = 1e-10      # fill: states below this fraction of the largest posterior are skipped
SWITCH_LIVE = 1e-3  # change of style: only states above this fraction of the largest posterior switch
PRUNE = 1e-8      # with style_switch > 0: posteriors below this fraction of the largest are set to 0
                  # (a style can come back through the switch, so nothing is lost for good; without
                  # the switch the filter stays exact, as the paper's)


def predict_shared(post: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``predict`` when every stream uses the same d (J,): one cyclic correlation in C."""
    J = d.shape[0]
    w = np.zeros(2 * J + 1)
    w[:J] = d[::-1]          # out[m] = sum_j d_j post[m - j]: weight d_j sits at offset -j
    return correlate1d(post, w, axis=-1, mode="wrap")


def predict(post: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(n, C, M) filtered -> (n, C, M) one-step prediction with per-stream d (n, J); eq. (1)."""
    out = np.zeros_like(post)
    for j in range(1, d.shape[1] + 1):
        out[..., j:] += post[..., :-j] * d[:, j - 1, None, None]
        out[..., :j] += post[..., -j:] * d[:, j - 1, None, None]
    return out


def prior(tab: FilterTables, state: dict[str, np.ndarray]) -> np.ndarray:
    """p(c, m | x_<t) for every stream (n, C, M)."""
    pr = switch_styles(predict(state["post"], state["d"]), tab.style_switch)
    first = state["t"] == 0
    if first.any():
        pr[first] = np.exp(tab.log_prior)
    return pr


def switch_styles(p: np.ndarray, h: float) -> np.ndarray:
    """(n, C, M) -> the same after a change of style with probability h, to any other style at the
    same phase: the styles' cycles are children of one parent cycle (eq. 5), so phase m means
    the same point of the gait in each.  h = 0 (the paper's model, one style per recording)
    returns p itself.  Without this a style whose posterior has underflowed to 0 can never
    return, so a performer who walks and then runs is filled as a walker for the rest of the take."""
    C = p.shape[-2]
    if h <= 0.0 or C < 2:
        return p
    # only states holding more than SWITCH_LIVE of the stream's largest mass change style (the rest
    # carry less than C M SWITCH_LIVE h of it): the states the switch creates stay few, so the
    # emission is evaluated on a compact support (see PRUNE)
    mx = p.reshape(p.shape[0], -1).max(1)[:, None, None] if p.ndim == 3 else p.max()
    src = np.where(p > SWITCH_LIVE * mx, p, 0.0)
    return p - h * src + (h / (C - 1)) * (src.sum(-2, keepdims=True) - src)


def _adapted(tab: FilterTables, state: dict[str, np.ndarray]) -> bool:
    """Weigh the emission on the stream's own cycle mu + delta instead of the style's mu?  Only
    with a change of style: then a style whose population cycle happens to fit the observed
    channels would otherwise win over the style this performer's cycle was learned in (an unseen
    subject flipped styles mid-gap and filled worse, gaps 02_01 RMS 10.7 -> 14.5; with it, 10.8).
    Without the switch the style cannot change and the population emission is as good
    (pan2009 0.295 against 0.301 x NN) and cheaper (no offsets on the whole support)."""
    return tab.kappa > 0.0 and tab.style_switch > 0.0 and "D" in state


def _update_one(tab: FilterTables, state: dict[str, np.ndarray], pr: np.ndarray, z: np.ndarray,
                zobs: np.ndarray, r: int = 0, keep: dict | None = None, want_ll: bool = True) -> np.ndarray | None:
    """``update`` of a lone stream without transition adaptation, given its prediction pr (C M,):
    the same arithmetic with fewer numpy calls.  r: the stream's row of D, W.  keep: receives the
    support and its offsets for ``fill`` (see there)."""
    rows = np.flatnonzero(pr)
    off: np.ndarray | None = None   # the adapted emission's offsets on rows (else the population emission)
    if zobs.any():
        if _adapted(tab, state):
            G = group_stats(state)
            E = knot_offsets(tab, state["D"][r], state["W"][r], *(G[k][r] for k in ("G", "GW") if G))
            a = tab.bin_a[rows, None]
            off = (1.0 - a) * E[tab.bin0[rows]] + a * E[tab.bin1[rows]]
            llp = adapted_loglik(tab, np.where(zobs[0], z[0], 0.0), zobs[0], rows, off)
            if keep is not None:
                keep["rows"], keep["off"] = rows, off
        else:
            llp = tab.em.fused_t[rows] @ tab.em.terms(z, zobs)[0]
        wp = np.exp(llp - llp.max())
    else:
        llp, wp = np.zeros(rows.size), np.ones(rows.size)
    newp = pr[rows] * wp
    if "ll" in state:   # the step's normaliser (init_state's "ll"), before any pruning
        nz = float(zobs[0].sum())
        state["ll"][0, :2] = (float(llp.max() + np.log(newp.sum())) if nz > 0 else 0.0, nz)   # ("ll" is not sparse: row 0)
        state["ll"][0, 2:] = _part_ll(tab, pr[rows], z, zobs, rows, off)
    if tab.style_switch > 0.0:
        newp[newp < PRUNE * newp.max()] = 0.0
    post = state["post"].reshape(-1)
    post[:] = 0.0
    post[rows] = newp / newp.sum()
    state["t"] += 1
    if not want_ll:
        return None
    ll = np.full(pr.shape[0], -np.inf)
    ll[rows] = llp
    return ll.reshape(state["post"].shape)


def _part_ll(tab: FilterTables, p: np.ndarray, z: np.ndarray, zobs: np.ndarray,
             rows: np.ndarray, off: np.ndarray | None) -> tuple[float, float]:
    """A lone stream's partial normaliser (init_state's "ll" columns 2-3): log sum_s p(s) b_s(z_t, o ∩ ll_feats)
    over the support rows (p: the prediction there) and the count of those features; (0, 0) with none.
    off: the adapted emission's offsets on rows (``_update_one``'s), None for the population emission."""
    lf = tab.ll_feats
    if lf.size == 0:
        return 0.0, 0.0
    zl = np.zeros_like(zobs)
    zl[:, lf] = zobs[:, lf]
    nl = float(zl[0].sum())
    if nl == 0:
        return 0.0, 0.0
    if off is not None:
        lq = adapted_loglik(tab, np.where(zl[0], z[0], 0.0), zl[0], rows, off)
    else:
        lq = tab.em.fused_t[rows] @ tab.em.terms(z, zl)[0]
    top = lq.max()
    return float(top + np.log((p * np.exp(lq - top)).sum())), nl


def _predict_one(tab: FilterTables, post: np.ndarray) -> np.ndarray:
    """``predict_shared`` and ``switch_styles`` of one stream (C M,) from its few nonzero states,
    with bincounts instead of passes over all C M states."""
    C, M = tab.shape
    rows = np.flatnonzero(post)
    d = tab.d_pop
    base = rows - rows % M                                           # c M of each state
    tgt = base + (rows % M + np.arange(1, d.size + 1)[:, None]) % M  # (J, k): m + j, wrapped in the cycle
    pr = np.bincount(tgt.ravel(), (d[:, None] * post[rows]).ravel(), minlength=C * M)
    h = tab.style_switch
    if h <= 0.0 or C < 2:
        return pr
    live = np.flatnonzero(pr > SWITCH_LIVE * pr.max())              # the states that change style
    v = h * pr[live]
    dest = (live % M) + M * np.arange(C)[:, None]                    # (C, ks): the same phase, each style
    pr += np.bincount(dest.ravel(), np.tile(v / (C - 1), C), minlength=C * M)
    pr[live] -= v + v / (C - 1)                                      # what left, and the own-style share
    return pr


def update(tab: FilterTables, state: dict[str, np.ndarray], z: np.ndarray, zobs: np.ndarray,
           prow: np.ndarray | None = None, keep: dict | None = None, want_ll: bool = True) -> np.ndarray | None:
    """Consume one frame per stream (z: (n, F) NaN where missing; zobs: (n, F) bool) and return
    the emission log-likelihoods ell (n, C, M) it used.  Updates ``state`` in place.

    The emission is evaluated only on the support of the prediction (states with p(c, m | x_<t) > 0,
    a few dozen of C M once the phase is known): elsewhere the posterior is 0 whatever the
    emission, so the result is the full recursion's, and ell is -inf there.  The weights are
    exp(ell - max over the support), so the best supported state has weight 1 and the product
    never underflows as a whole."""
    post, d = state["post"], state["d"]
    first = state["t"] == 0
    n = z.shape[0]
    if n == 1 and tab.adapt_rate == 0.0:
        pr1 = np.exp(tab.log_prior).reshape(-1) if first[0] else _predict_one(tab, post.reshape(-1))
        return _update_one(tab, state, pr1, z, zobs, 0 if prow is None else prow[0], keep, want_ll)
    anyobs = zobs.any(1)
    if tab.adapt_rate > 0.0:
        # P(jump = j | x_<=t) needs the per-jump split of the prediction
        parts = np.zeros((d.shape[1], n) + tab.shape)
        for j in range(1, d.shape[1] + 1):
            parts[j - 1][..., j:] = post[..., :-j] * d[:, j - 1, None, None]
            parts[j - 1][..., :j] = post[..., -j:] * d[:, j - 1, None, None]
        pr = parts.sum(0)
    elif tab.adapt_rate == 0.0:
        pr = predict_shared(post, tab.d_pop)      # d never leaves d_pop without adaptation
    else:
        pr = predict(post, d)
    pr = switch_styles(pr, tab.style_switch)
    if first.any():
        pr[first] = np.exp(tab.log_prior)
    prf = pr.reshape(n, -1)
    adapted = _adapted(tab, state)
    si, rows = np.nonzero(prf > 0.0)               # the support, grouped by stream
    p = prf[si, rows]
    if anyobs.any():
        if adapted:
            # the emission on the stream's own cycle (module doc, "Stream cycle adaptation")
            off = pair_offsets(tab, state["D"], state["W"], si if prow is None else prow[si], rows, **group_stats(state))
            llp = adapted_loglik(tab, np.where(zobs, z, 0.0)[si], zobs[si], rows, off)
        else:
            llp = tab.em.loglik_at(tab.em.terms(z, zobs), si, rows)
        llp[~anyobs[si]] = 0.0                       # nothing observed: a pure prediction step
    else:
        llp = np.zeros(si.size)
    starts = _runs(si)
    which = np.repeat(np.arange(starts.size), np.diff(np.append(starts, si.size)))
    wp = np.exp(llp - np.maximum.reduceat(llp, starts)[which])
    newp = p * wp
    if "ll" in state:   # each stream's normaliser (init_state's "ll"), before any pruning
        nz = zobs.sum(1).astype(float)
        lln = np.maximum.reduceat(llp, starts) + np.log(np.add.reduceat(newp, starts))
        state["ll"][si[starts], 0] = np.where(nz[si[starts]] > 0, lln, 0.0)
        state["ll"][:, 1] = nz
        lf = tab.ll_feats   # columns 2-3: the same over the observed features of ll_feats only (_part_ll)
        state["ll"][:, 2:] = 0.0
        if lf.size:   # (none asked for: no extra work, as the compiled step)
            zl = np.zeros_like(zobs)
            zl[:, lf] = zobs[:, lf]
            nl = zl.sum(1).astype(float)
            if nl.any():
                if adapted:
                    lq = adapted_loglik(tab, np.where(zl, z, 0.0)[si], zl[si], rows, off)
                else:
                    lq = tab.em.loglik_at(tab.em.terms(z, zl), si, rows)
                top = np.maximum.reduceat(lq, starts)
                lnl = top + np.log(np.add.reduceat(p * np.exp(lq - top[which]), starts))
                state["ll"][si[starts], 2] = np.where(nl[si[starts]] > 0, lnl, 0.0)
            state["ll"][:, 3] = nl
    if tab.style_switch > 0.0:
        newp[newp < PRUNE * np.maximum.reduceat(newp, starts)[which]] = 0.0
    tot = np.add.reduceat(newp, starts)
    post.reshape(n, -1)[...] = 0.0
    post.reshape(n, -1)[si, rows] = newp / tot[which]
    ll = None
    if want_ll:   # only the fixed-lag smoother reads it; the daemon's step does not
        ll = np.full((n, prf.shape[1]), -np.inf)
        ll[si, rows] = llp
        ll = ll.reshape(pr.shape)
    if tab.adapt_rate > 0.0:
        w = np.zeros_like(prf)
        w[si, rows] = wp
        xi = (parts * w.reshape(pr.shape)[None]).sum(axis=(2, 3)).T       # (n, J)
        xi /= np.maximum(xi.sum(1, keepdims=True), 1e-300)
        xi[first | ~anyobs] = 0.0    # no information about the jump in these frames
        state["counts"] *= 1.0 - tab.adapt_rate
        state["counts"] += xi
        dn = tab.prior_strength * tab.d_pop[None] + state["counts"]
        state["d"][...] = dn / dn.sum(1, keepdims=True)
    state["t"] += 1
    return ll


def fill(tab: FilterTables, P: np.ndarray, z: np.ndarray, zobs: np.ndarray, R: np.ndarray | None = None,
         W: np.ndarray | None = None, prow: np.ndarray | None = None,
         keep: dict | None = None, G: np.ndarray | None = None,
         GW: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fill the missing features from a joint posterior P (n, C, M).  Returns (z completed, std),
    both (n, F); std is 0 where observed.  R, W (n, C*n_bins, F): the stream-cycle statistics D, W, if adapting;
    with prow (n,) they are a state pool's arrays and stream i owns row prow[i] (see ``accumulate``).

    Eq. (18) with the joint posterior in place of psi(c) gamma(m):
    x_dag = (sum_c P(c) Lambda^c)^-1 sum_cm P(c, m) Lambda^c mu^{c,m}.  Only states holding more
    than LIVE of the largest posterior enter the sums (the rest carry < C M LIVE of the mass), so a
    frame costs O(k F) for k live states.  Vectorised over the batch: the live (stream, state)
    pairs of all streams with something missing are gathered at once and summed per stream.
    """
    out = z.copy()
    sd = np.zeros_like(z)
    F = z.shape[1]
    miss = ~zobs
    sel = np.flatnonzero(miss.any(1))
    if sel.size == 0:
        return out, sd
    if sel.size == 1:
        # a lone stream: the direct path costs fewer numpy calls than the batched gather
        i = sel[0]
        Pf = P[i].reshape(-1)
        rows = np.flatnonzero(Pf > LIVE * Pf.max())
        p = Pf[rows] / Pf[rows].sum()
        if R is None:
            s4 = p @ tab.pack[rows]
            val, mean, m2 = s4[:F] / s4[F : 2 * F], s4[2 * F : 3 * F], s4[3 * F :]
        else:
            if keep and "off" in keep:
                # the offsets ``update`` computed on the prediction's support (which holds every
                # live state) before this frame was added to R, W: this frame only adds to the
                # observed features' columns, so for the missing ones, the only ones filled, they
                # are the same numbers
                off = keep["off"][np.searchsorted(keep["rows"], rows)]
            else:
                r = i if prow is None else prow[i]
                off = tab.knot_weights[rows] @ knot_offsets(tab, R[r], W[r], *((G[r], GW[r]) if G is not None else ()))
            mu = tab.mu[rows] + off
            lam = tab.lam_rows[rows]
            val = (p @ (lam * mu)) / (p @ lam)
            mean, m2 = p @ mu, p @ (mu * mu + tab.var_q[rows])
        var = np.maximum(m2 - mean * mean, 0.0) + (mean - val) ** 2
        out[i, miss[i]] = val[miss[i]]
        sd[i, miss[i]] = np.sqrt(var[miss[i]])
        return out, sd
    s, rows, p = _live(P, sel, LIVE)
    starts = _runs(s)                                             # first pair of each stream in sel
    p = p / np.add.reduceat(p, starts)[np.repeat(np.arange(starts.size), np.diff(np.append(starts, s.size)))]

    def S(X: np.ndarray) -> np.ndarray:
        """Per-stream sums sum_k p_k X_k (n_sel, ...) over the contiguous runs of each stream."""
        return (p @ X)[None] if starts.size == 1 else np.add.reduceat(p[:, None] * X, starts)

    if R is None:
        # one gather of the packed per-state table [lam mu | lam | mu | mu^2 + var + 1/lam]
        s4 = S(tab.pack[rows])                                                # (n_sel, 4F)
        val = s4[:, :F] / s4[:, F : 2 * F]
        mean, m2 = s4[:, 2 * F : 3 * F], s4[:, 3 * F :]
    else:
        # the stream's own cycle: style cycle plus the stream's offset (module doc)
        off = pair_offsets(tab, R, W, s if prow is None else prow[s], rows, G, GW)
        mu = tab.mu[rows] + off
        lam = tab.lam_rows[rows]
        val = S(lam * mu) / S(lam)
        mean = S(mu)
        m2 = S(mu * mu + tab.var_q[rows])
    var = np.maximum(m2 - mean * mean, 0.0) + (mean - val) ** 2
    ms = miss[sel]
    out[sel] = np.where(ms, val, z[sel])
    sd[sel] = np.where(ms, np.sqrt(var), 0.0)
    return out, sd


def extras(tab: FilterTables, P: np.ndarray) -> list[dict]:
    """Style posterior and circular-mean phase in [0, 1) for each row of P (n, C, M)."""
    Pc = P.sum(2)
    Pm = P.sum(1)
    ph = np.arctan2(Pm @ tab.sin, Pm @ tab.cos) / (2.0 * np.pi) % 1.0
    return [{"style": Pc[i].tolist(), "phase": float(ph[i])} for i in range(P.shape[0])]


def smooth_lag(post_buf: np.ndarray, ll_buf: np.ndarray, d: np.ndarray, style_switch: float = 0.0) -> np.ndarray:
    """Fixed-lag smoothing: the posterior of the oldest buffered frame given all buffered frames.

    post_buf : (L+1, n, C, M) filtered posteriors, oldest first.  ll_buf : (L+1, n, C, M) their
    emission log-likelihoods.  d : (n, J).  Returns (n, C, M).  O(L C M J): constant per frame.
    """
    L1 = post_buf.shape[0]
    beta = np.ones(post_buf.shape[1:])
    for u in range(L1 - 1, 0, -1):
        w = np.exp(ll_buf[u] - ll_buf[u].max(axis=(1, 2), keepdims=True)) * beta
        nb = np.zeros_like(beta)
        for j in range(1, d.shape[1] + 1):
            # beta_{u-1}(m) = sum_j d_j w_u(m + j) beta_u(m + j)
            nb[..., :-j] += w[..., j:] * d[:, j - 1, None, None]
            nb[..., -j:] += w[..., :j] * d[:, j - 1, None, None]
        # the change of style acts on the style axis and the jump on the phase axis: they commute
        nb = switch_styles(nb, style_switch)
        beta = nb / np.maximum(nb.max(axis=(1, 2), keepdims=True), 1e-300)
    sm = post_buf[0] * beta
    return sm / np.maximum(sm.sum(axis=(1, 2), keepdims=True), 1e-300)
