"""Sampling from the HLM's own generative process (section 2), for tests and offline demos.

``random_params`` draws a smooth parent cycle and style cycles around it; ``sample`` then follows
steps 4a-4d: a style label per sequence, its transition probabilities d^k, a phase path by eq. (1)
and Gaussian emissions around the style's latent cycle.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Truth:
    """What generated a synthetic data set.  Z : (C, M, F) style cycles.  lam : (C, F).
    labels : (K,).  paths : list of (N_k,) phase indices.  d : (K, J)."""

    Z: np.ndarray
    lam: np.ndarray
    labels: np.ndarray
    paths: list[np.ndarray]
    d: np.ndarray


def random_cycles(n_styles: int, n_states: int, n_features: int, rng: np.random.Generator,
                  style_spread: float = 1.0, harmonics: int = 3) -> np.ndarray:
    """(C, M, F) smooth periodic cycles: a shared parent plus a smooth per-style deviation."""
    m = 2.0 * np.pi * np.arange(n_states) / n_states

    def smooth(scale: float) -> np.ndarray:
        out = np.zeros((n_states, n_features))
        for h in range(1, harmonics + 1):
            a, b = rng.normal(0.0, scale / h, (2, n_features))
            out += np.outer(np.cos(h * m), a) + np.outer(np.sin(h * m), b)
        return out

    parent = smooth(2.0)
    return np.stack([parent + smooth(style_spread) + rng.normal(0.0, style_spread, n_features)
                     for _ in range(n_styles)])


def sample(Z: np.ndarray, lam: np.ndarray, lengths: list[int], rng: np.random.Generator,
           tau: np.ndarray | None = None, d_alpha: tuple[float, ...] = (2.0, 6.0, 2.0),
           labels: np.ndarray | None = None) -> tuple[list[np.ndarray], Truth]:
    """Draw sequences x^k (N_k, F) from the generative process with cycles Z (C, M, F) and noise
    precisions lam (C, F).  ``d_alpha`` is the Dirichlet the d^k are drawn from (J = its length)."""
    C, M, F = Z.shape
    K = len(lengths)
    tau = np.full(C, 1.0 / C) if tau is None else tau
    labels = rng.choice(C, size=K, p=tau) if labels is None else np.asarray(labels)
    J = len(d_alpha)
    d = rng.dirichlet(d_alpha, size=K)
    seqs, paths = [], []
    for k, n in enumerate(lengths):
        path = np.empty(n, dtype=int)
        path[0] = rng.integers(M)
        jumps = rng.choice(np.arange(1, J + 1), size=n - 1, p=d[k])
        path[1:] = (path[0] + np.cumsum(jumps)) % M
        c = labels[k]
        x = Z[c, path] + rng.normal(size=(n, F)) / np.sqrt(lam[c])
        seqs.append(x)
        paths.append(path)
    return seqs, Truth(Z, lam, labels, paths, d)
