"""Forward-backward and Viterbi over the cyclic left-to-right transitions of eq. (1), in log space.

From state n the phase moves to m = n + j (mod M) with probability d_j, j = 1..J: there is no
self-transition.  The transition matrix is never built: each step is a logsumexp over J shifted
copies of the previous message, so a pass costs O(T x batch x M x J).

Batching: every function takes emissions ``log_e`` of shape (T, *batch, M); the batch axes are
sequences (training: one HMM per sequence over M phases) or (streams, styles) for the joint
(style, phase) chain used at test time.  Sequences of different lengths are padded; padding
frames must carry log_e = 0 (an uninformative emission), which leaves the backward messages of
the real frames exact (transitions sum to one), so lengths only matter for log Z.
"""
from __future__ import annotations

import numpy as np


def _lse_shift(msg: np.ndarray, log_d: np.ndarray, sign: int, buf: np.ndarray) -> np.ndarray:
    """out[..., m] = logsumexp_j (msg[..., m - sign*j] + log_d[..., j-1]), cyclic in m.

    msg: (*batch, M); log_d: (*batch, J) (broadcastable); buf: (J, *batch, M) scratch.
    """
    J = buf.shape[0]
    for j in range(1, J + 1):
        # np.roll(msg, sign*j, -1) without the allocation
        k = j if sign > 0 else -j
        b = buf[j - 1]
        b[..., k % msg.shape[-1]:] = msg[..., : msg.shape[-1] - k % msg.shape[-1]]
        b[..., : k % msg.shape[-1]] = msg[..., msg.shape[-1] - k % msg.shape[-1]:]
        b += log_d[..., j - 1 : j]
    mx = buf.max(0)
    # states unreachable from every predecessor give -inf; keep them -inf without a warning
    safe = np.where(np.isfinite(mx), mx, 0.0)
    with np.errstate(divide="ignore"):  # log(0) = -inf for unreachable states is intended
        return np.log(np.exp(buf - safe).sum(0)) + safe


def forward(log_e: np.ndarray, log_start: np.ndarray, log_d: np.ndarray) -> np.ndarray:
    """Log forward messages log alpha_t = log p(x_1..t, state_t), shape like log_e (T, *batch, M).

    log_start: (*batch, M) log p(state_1).  log_d: (*batch_or_1, J) log transition probabilities.
    """
    T = log_e.shape[0]
    J = log_d.shape[-1]
    la = np.empty_like(log_e)
    la[0] = log_start + log_e[0]
    buf = np.empty((J,) + log_e.shape[1:])
    for t in range(1, T):
        la[t] = _lse_shift(la[t - 1], log_d, +1, buf) + log_e[t]
    return la


def backward(log_e: np.ndarray, log_d: np.ndarray) -> np.ndarray:
    """Log backward messages log beta_t = log p(x_{t+1}..T | state_t), shape like log_e."""
    T = log_e.shape[0]
    J = log_d.shape[-1]
    lb = np.empty_like(log_e)
    lb[-1] = 0.0
    buf = np.empty((J,) + log_e.shape[1:])
    for t in range(T - 2, -1, -1):
        lb[t] = _lse_shift(lb[t + 1] + log_e[t + 1], log_d, -1, buf)
    return lb


def forward_backward(log_e: np.ndarray, log_start: np.ndarray, log_d: np.ndarray,
                     lengths: np.ndarray | None = None):
    """Smoothed posteriors of a batch of sequences over one phase axis (training's Q(pi^k)).

    log_e : (T, K, M) padded emissions (0 on padding).  log_start : (K, M).  log_d : (K, J).
    lengths : (K,) real frames per sequence.

    Returns gamma (T, K, M) (0 on padding), log_z (K,), jumps (K, J) = expected number of
    transitions of length j, the sums over xi in eq. (16).  The jump counts are accumulated inside
    the backward loop from the forward messages, so no (T, K, M, J) array is ever formed.
    """
    T, K, M = log_e.shape
    J = log_d.shape[-1]
    lengths = np.full(K, T) if lengths is None else np.asarray(lengths)
    la = forward(log_e, log_start, log_d)
    last = la[lengths - 1, np.arange(K)]                          # (K, M)
    log_z = logsumexp(last, axis=-1)
    # gamma is formed in place of alpha, step by step, so no beta array is ever stored
    gamma = la
    lb = np.zeros((K, M))
    buf = np.empty((J, K, M))
    jumps = np.zeros((K, J))
    with np.errstate(under="ignore"):  # tiny posteriors and negligible transitions underflow to 0
        gamma[T - 1] = np.exp(np.minimum(la[T - 1] - log_z[:, None], 0.0))
        for t in range(T - 2, -1, -1):
            lb_next = lb
            lb = _lse_shift(lb_next + log_e[t + 1], log_d, -1, buf)
            live = (t + 1) < lengths                               # transition t -> t+1 is real
            if live.any():
                # xi_t(n -> n+j) = alpha_t(n) d_j e_{t+1}(n+j) beta_{t+1}(n+j) / Z; buf holds the last three
                x = np.exp(np.minimum(buf + la[t] - log_z[:, None], 0.0)).sum(-1)   # (J, K)
                jumps += np.where(live[:, None], x.T, 0.0)
            gamma[t] = np.exp(np.minimum(la[t] + lb - log_z[:, None], 0.0))
    valid = np.arange(T)[:, None] < lengths[None, :]
    gamma[~valid] = 0.0
    return gamma, log_z, jumps


def logsumexp(x: np.ndarray, axis=None, keepdims: bool = False) -> np.ndarray:
    mx = np.max(x, axis=axis, keepdims=True)
    mx = np.where(np.isfinite(mx), mx, 0.0)
    out = np.log(np.exp(x - mx).sum(axis=axis, keepdims=True)) + mx
    return out if keepdims else np.squeeze(out, axis=axis) if axis is not None else out.reshape(())


def posteriors(la: np.ndarray, lb: np.ndarray, log_e: np.ndarray, log_d: np.ndarray,
               lengths: np.ndarray | None = None, state_axes: int = 1):
    """Smoothed marginals, log Z and expected jump counts.

    Parameters
    ----------
    la, lb, log_e : (T, *batch, *states) with the last axis the phase M.  ``state_axes`` is how
        many trailing axes make up one state (1: phase only; 2: (style, phase)).
    log_d : (*batch, J) broadcastable.
    lengths : (*batch,) frames of each padded sequence (default: all T).

    Returns
    -------
    gamma : (T, *batch, *states) posterior state probabilities (zero on padding).
    log_z : (*batch,) log-likelihood of each sequence.
    jumps : (*batch, J) expected number of transitions of length j (eq. 16's sums over xi).
    """
    T = la.shape[0]
    batch = la.shape[1 : la.ndim - state_axes]
    if lengths is None:
        lengths = np.full(batch, T)
    lengths = np.asarray(lengths)
    nb = len(batch)
    last = np.take_along_axis(la, (lengths - 1).reshape((1,) + batch + (1,) * state_axes), 0)[0]
    log_z = logsumexp(last, axis=tuple(range(nb, nb + state_axes)))
    ze = log_z.reshape(batch + (1,) * state_axes)
    valid = (np.arange(T).reshape((T,) + (1,) * len(batch)) < lengths)  # (T, *batch)
    vexp = valid.reshape(valid.shape + (1,) * state_axes)
    with np.errstate(under="ignore"):  # tiny posteriors underflowing to 0 is fine
        gamma = np.where(vexp, np.exp(np.minimum(la + lb - ze, 0.0)), 0.0)
    J = log_d.shape[-1]
    jumps = np.zeros(batch + (J,))
    if T > 1:
        nxt = lb[1:] + log_e[1:]                        # (T-1, *batch, *states)
        ld = np.broadcast_to(log_d, batch + (J,))
        for j in range(1, J + 1):
            # xi_t(n -> n+j) = alpha_{t-1}(n) d_j e_t(n+j) beta_t(n+j) / Z
            lx = la[:-1] + np.roll(nxt, -j, axis=-1) + ld[..., j - 1].reshape((1,) + batch + (1,) * state_axes) - ze
            with np.errstate(under="ignore"):
                xi = np.exp(np.minimum(lx, 0.0))
            xi = np.where(vexp[1:], xi, 0.0)
            jumps[..., j - 1] = xi.sum(axis=(0,) + tuple(range(1 + nb, 1 + nb + state_axes)))
    return gamma, log_z, jumps


def viterbi(log_e: np.ndarray, log_start: np.ndarray, log_d: np.ndarray) -> tuple[np.ndarray, float]:
    """Most probable state path of one sequence.  log_e: (T, *states) with the phase last,
    log_start: (*states), log_d: (J,).  Returns (path (T, len(states)) of indices, log prob)."""
    T = log_e.shape[0]
    sshape = log_e.shape[1:]
    M = sshape[-1]
    J = log_d.shape[-1]
    delta = log_start + log_e[0]
    back = np.zeros((T,) + sshape, dtype=np.int8)
    for t in range(1, T):
        cand = np.stack([np.roll(delta, j, axis=-1) + log_d[j - 1] for j in range(1, J + 1)])
        back[t] = cand.argmax(0)
        delta = cand.max(0) + log_e[t]
    flat = int(np.argmax(delta))
    best = float(delta.reshape(-1)[flat])
    idx = np.array(np.unravel_index(flat, sshape))
    path = np.zeros((T, len(sshape)), dtype=int)
    path[-1] = idx
    for t in range(T - 1, 0, -1):
        j = int(back[(t,) + tuple(idx)]) + 1
        idx = idx.copy()
        idx[-1] = (idx[-1] - j) % M
        path[t - 1] = idx
    return path, best
