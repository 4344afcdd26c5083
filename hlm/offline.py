"""Offline use of a trained HLM on a whole recording: style and phase posteriors, Viterbi
alignment, fill by eq. (18) with the smoothed posteriors, and style-clustering purity.

Test-time inference runs forward-backward over the joint (style, phase) state with Q(Z) plugged
in: with the style fixed per sequence this is the exact posterior of the trained model (the
mean-field split Q(l) Q(pi) of training is an approximation of it; the two agree when the style
posterior is certain).  The sequence's own transition probabilities d are re-estimated by a few
EM steps of eq. (16) starting from the population d (the sequence is new, so it has no d^k).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hlm import hmm
from hlm.online import FilterTables, fill


@dataclass
class Posterior:
    """P : (T, C, M) smoothed joint posterior.  style : (C,).  phase : (T,) in [0, 1).
    d : (J,) transition probabilities used.  log_z : log-likelihood of the observed entries."""

    P: np.ndarray
    style: np.ndarray
    phase: np.ndarray
    d: np.ndarray
    log_z: float


def forward_filter(tab: FilterTables, z: np.ndarray, zobs: np.ndarray, d: np.ndarray | None = None) -> np.ndarray:
    """Normalised log-space forward messages p(c, m | x_<=t), (T, C, M), with fixed d (J,)."""
    d = tab.d_pop if d is None else d
    ll = tab.em.loglik(z, zobs)
    la = hmm.forward(ll, tab.log_prior, np.log(d)[None])
    la -= hmm.logsumexp(la, axis=(1, 2), keepdims=True)
    return np.exp(la)


def infer(tab: FilterTables, z: np.ndarray, zobs: np.ndarray, n_iter_d: int = 3, eta: float = 0.1) -> Posterior:
    """Smoothed joint posterior of one recording.  z: (T, F) features (NaN where missing); zobs: (T, F)."""
    ll = tab.em.loglik(z, zobs)                             # (T, C, M)
    d = tab.d_pop.copy()
    for it in range(max(1, n_iter_d + 1)):
        log_d = np.log(d)                                   # one d for every style
        la = hmm.forward(ll, tab.log_prior, log_d)
        lb = hmm.backward(ll, log_d)
        P, log_z, jumps = hmm.posteriors(la, lb, ll, log_d, None, state_axes=2)
        if it == n_iter_d:
            break
        dd = eta + jumps                              # eq. (16) with the Dirichlet(1 + eta) prior
        d = dd / dd.sum()
    P = P / P.sum(axis=(1, 2), keepdims=True)
    Pm = P.sum(1)
    ph = np.arctan2(Pm @ tab.sin, Pm @ tab.cos) / (2.0 * np.pi) % 1.0
    return Posterior(P, P.sum(2).mean(0), ph, d, float(log_z))


def fill_features(tab: FilterTables, z: np.ndarray, zobs: np.ndarray, n_iter_d: int = 3,
                  cond: Any = None) -> tuple[np.ndarray, np.ndarray, Posterior]:
    """Fill a whole recording in feature space by eq. (18) with the smoothed posteriors.
    Returns (z completed (T, F), std (T, F), posterior).  With ``tab.kappa > 0`` the recording's
    own cycle (see ``hlm.online``) is estimated from all its observed frames and the smoothed
    posteriors, then used in (18).  ``cond`` (``hlm.condfill.CondTables``): each frame's fill is
    then corrected from its observed features' residuals, as the online filter's is."""
    post = infer(tab, z, zobs, n_iter_d)
    zf, sd, stats = _fill18(tab, z, zobs, post)
    if cond is not None:
        from hlm import condfill

        for t in np.flatnonzero(zobs.any(1) & ~zobs.all(1)):
            st = {"post": post.P[t : t + 1], **stats}
            condfill.correct(tab, cond, st, z[t : t + 1], zobs[t : t + 1], zf[t : t + 1])
    return zf, sd, post


def _fill18(tab: FilterTables, z: np.ndarray, zobs: np.ndarray, post: Posterior) -> tuple[np.ndarray, np.ndarray, dict]:
    """eq. (18) over the smoothed posteriors; returns the recording's cycle statistics too."""
    if tab.kappa > 0.0:
        T = z.shape[0]
        C, M = tab.shape
        P = post.P.reshape(T, C * M)
        A = np.zeros((C * M, C * tab.n_bins))                   # state -> knot interpolation weights
        A[np.arange(C * M), tab.bin0] += 1.0 - tab.bin_a
        A[np.arange(C * M), tab.bin1] += tab.bin_a
        o = zobs.astype(np.float64)
        Pb = P @ A
        # D_b = sum_t sum_m P_t(m) A(m, b) o_t (x_t - mu_m);  W_b = sum_t sum_m P_t(m) A(m, b) o_t
        D = Pb.T @ (o * np.where(zobs, z, 0.0)) - A.T @ (tab.mu * (P.T @ o))
        W = Pb.T @ o
        zf, sd = fill(tab, post.P, z, zobs, D[None].repeat(T, 0), W[None].repeat(T, 0))
        return zf, sd, {"D": D[None], "W": W[None]}
    zf, sd = fill(tab, post.P, z, zobs)
    return zf, sd, {}


def viterbi(tab: FilterTables, z: np.ndarray, zobs: np.ndarray, d: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Most probable (style, phase) path: returns (style (T,), phase state (T,)).  The style is
    constant along a path (a sequence has one style, step 4a)."""
    d = tab.d_pop if d is None else d
    ll = tab.em.loglik(z, zobs)
    path, _ = hmm.viterbi(ll, tab.log_prior, np.log(d))
    return path[:, 0], path[:, 1]


def purity(assign: Sequence[int], labels: Sequence) -> float:
    """Average cluster purity (the paper's footnote 4): sum over clusters of the size of the
    majority true class in it, divided by the number of items."""
    assign = np.asarray(assign)
    labels = np.asarray(labels)
    if assign.shape != labels.shape:
        raise ValueError(f"{assign.shape[0]} assignments for {labels.shape[0]} labels")
    tot = 0
    for c in np.unique(assign):
        _, counts = np.unique(labels[assign == c], return_counts=True)
        tot += counts.max()
    return tot / max(len(labels), 1)
