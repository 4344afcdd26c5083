"""Symmetric cyclic tridiagonal systems, batched: the precision matrices of the HLM latent cycles.

Both Gaussians of the HLM that live on the cycle have this shape:

* the variational posterior ``Q(z^{c,f})`` (section 3.1) with precision
  ``S_mm = 2 lambda_s + lambda_zbar + lambda_f^c W_cm``, ``S_{m,m+1} = S_{1,M} = -lambda_s``;
* the parent-cycle system of eq. (17), ``(C lambda_zbar + 4 eta) zbar_m - 2 eta zbar_{m-1}
  - 2 eta zbar_{m+1} = lambda_zbar sum_c <z_m^c>`` (cyclic, so the same pattern with s = 2 eta).

A = diag(a) - s (sub + super + the two corners).  We split A = T + s w w^T with
w = e_1 - e_M and T the open-chain tridiagonal (ends reduced by s), factor T = L D L^T in O(M)
and use Sherman-Morrison for the corner.  Everything is exact (no iteration), O(M) per system
and vectorised over the batch axis: arrays are laid out (M, B) so the O(M) loops walk over
contiguous rows.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class CyclicFactor:
    """Factorisation of B cyclic tridiagonal matrices of size M.

    d, l : (M, B) and (M - 1, B): T = L D L^T, L unit lower bidiagonal with L_{m+1,m} = l_m.
    s : (B,) off-diagonal magnitude.  g : (M, B) = T^{-1} w.  denom : (B,) = 1 + s w^T T^{-1} w.
    """

    d: np.ndarray
    l: np.ndarray
    s: np.ndarray
    g: np.ndarray
    denom: np.ndarray
    corner: np.ndarray  # (B,) (T^{-1})_{1,M}

    @property
    def M(self) -> int:
        return self.d.shape[0]

    def _solve_T(self, b: np.ndarray) -> np.ndarray:
        """T^{-1} b for b of shape (M, B) or (M, B, k)."""
        d, l = self.d, self.l
        if b.ndim == 3:
            d, l = d[..., None], l[..., None]
        y = np.empty_like(b)
        y[0] = b[0]
        for m in range(self.M - 1):
            y[m + 1] = b[m + 1] - l[m] * y[m]
        x = y
        x[-1] = y[-1] / d[-1]
        for m in range(self.M - 2, -1, -1):
            x[m] = y[m] / d[m] - l[m] * x[m + 1]
        return x

    def solve(self, b: np.ndarray) -> np.ndarray:
        """A^{-1} b, b: (M, B) or (M, B, k)."""
        y = self._solve_T(np.array(b, dtype=np.float64, copy=True))
        g, s, den = self.g, self.s, self.denom
        if y.ndim == 3:
            g, s, den = g[..., None], s[..., None], den[..., None]
        # Sherman-Morrison: A^{-1} b = T^{-1} b - s g (w^T T^{-1} b) / (1 + s w^T g)
        return y - g * (s * (y[0] - y[-1]) / den)

    def marginals(self) -> tuple[np.ndarray, np.ndarray]:
        """Diagonal of A^{-1} (M, B) and its cyclic lag-one entries (A^{-1})_{m, m+1 mod M} (M, B)."""
        M = self.M
        d, l = self.d, self.l
        diag = np.empty_like(d)
        sup = np.empty_like(d)
        diag[-1] = 1.0 / d[-1]
        for m in range(M - 2, -1, -1):
            # Takahashi recursion for Sigma = T^{-1}: Sigma_{m,m+1} = -l_m Sigma_{m+1,m+1},
            # Sigma_mm = 1/d_m - l_m Sigma_{m+1,m}
            sup[m] = -l[m] * diag[m + 1]
            diag[m] = 1.0 / d[m] - l[m] * sup[m]
        sup[-1] = self.corner
        g, k = self.g, self.s / self.denom
        diag -= k * g * g
        sup[:-1] -= k * g[:-1] * g[1:]
        sup[-1] -= k * g[-1] * g[0]
        return diag, sup

    def logdet(self) -> np.ndarray:
        """log det A (B,) by the matrix determinant lemma."""
        return np.log(self.d).sum(0) + np.log(self.denom)


def factor(a: np.ndarray, s: np.ndarray | float) -> CyclicFactor:
    """Factor A = diag(a) - s (cyclic neighbours).  a: (M, B) with M >= 3; s: scalar or (B,), s >= 0.

    A must be positive definite: a_m > 2 s everywhere suffices (true for every use here).
    """
    a = np.asarray(a, dtype=np.float64)
    M, B = a.shape
    if M < 3:
        raise ValueError(f"a cyclic system needs at least 3 states (got M={M})")
    s = np.broadcast_to(np.asarray(s, dtype=np.float64), (B,)).copy()
    t = a.copy()
    t[0] -= s
    t[-1] -= s
    d = np.empty_like(t)
    l = np.empty((M - 1, B))
    d[0] = t[0]
    for m in range(M - 1):
        l[m] = -s / d[m]
        d[m + 1] = t[m + 1] - s * s / d[m]
    f = CyclicFactor(d, l, s, np.zeros((M, B)), np.ones(B), np.zeros(B))
    e = np.zeros((M, B, 2))
    e[0, :, 0] = 1.0
    e[-1, :, 1] = 1.0
    cols = f._solve_T(e)           # T^{-1} e_1, T^{-1} e_M
    f.g = cols[..., 0] - cols[..., 1]
    f.corner = cols[0, :, 1]
    f.denom = 1.0 + s * (f.g[0] - f.g[-1])
    return f


def dense(a: np.ndarray, s: np.ndarray | float) -> np.ndarray:
    """The matrices themselves (B, M, M), for tests."""
    a = np.asarray(a, dtype=np.float64)
    M, B = a.shape
    s = np.broadcast_to(np.asarray(s, dtype=np.float64), (B,))
    A = np.zeros((B, M, M))
    idx = np.arange(M)
    A[:, idx, idx] = a.T
    A[:, idx, (idx + 1) % M] -= s[:, None]
    A[:, (idx + 1) % M, idx] -= s[:, None]
    return A
