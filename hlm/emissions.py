"""Expected Gaussian emission log-likelihoods of the HLM, batched over styles x phases.

For frame x with observed mask o, style c and latent-cycle state m,

    ell(c, m) = < log N(x_o ; z^c_{m,o}, (Lambda^c_o)^{-1}) >_{Q(z^c_m)}
              = sum_{f observed} [ 1/2 log lambda^c_f - 1/2 log 2 pi
                                   - lambda^c_f / 2 ((x_f - mu^c_{mf})^2 + var^c_{mf}) ]

which is the bracket of eq. (10) and of eq. (11), with the constants kept so the same numbers
enter the lower bound.  (Eq. (10) as printed has "- sum_f log lambda_f^c" outside the expectation;
the Gaussian normaliser is +1/2 sum_f log lambda_f^c, constant in m, so it does not change Q(pi)
but it does change the bound and eq. (11), which prints the correct (lambda)^(N/2).)

Expanded into matrix products so a whole recording or a batch of streams costs a few GEMMs:
  -1/2 (o x^2) . lambda  +  (o x) . (lambda mu)  -  1/2 o . lambda (mu^2 + var)  +  1/2 o . (log lambda - log 2 pi)
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LOG2PI = float(np.log(2.0 * np.pi))


@dataclass
class EmissionTables:
    """Precomputed per-(style, phase) tables.  C styles, M phases, F features.

    lam : (C, F).  lam_mu : (C*M, F).  lam_q : (C*M, F) = lam (mu^2 + var).
    log_norm : (C, F) = 1/2 (log lam - log 2 pi).
    """

    C: int
    M: int
    lam: np.ndarray
    lam_mu: np.ndarray
    lam_q: np.ndarray
    log_norm: np.ndarray
    fused: np.ndarray | None = None   # (3F, C*M): rows for [x, o, x^2]: one GEMM for every term
    fused_t: np.ndarray | None = None  # (C*M, 3F): the same, a row per state, for a few states at a time

    @classmethod
    def build(cls, mu: np.ndarray, var: np.ndarray, lam: np.ndarray) -> EmissionTables:
        """mu, var: (C, M, F); lam: (C, F)."""
        C, M, F = mu.shape
        lam3 = lam[:, None, :]
        lam_mu = np.ascontiguousarray((lam3 * mu).reshape(C * M, F))
        lam_q = np.ascontiguousarray((lam3 * (mu * mu + var)).reshape(C * M, F))
        log_norm = 0.5 * (np.log(lam) - LOG2PI)
        per_o = -0.5 * lam_q + np.repeat(log_norm, M, axis=0)        # (C*M, F) weight of o_f
        per_x2 = -0.5 * np.repeat(lam, M, axis=0)                      # (C*M, F) weight of x_f^2
        return cls(C, M, np.ascontiguousarray(lam), lam_mu, lam_q, log_norm,
                   np.ascontiguousarray(np.hstack([lam_mu, per_o, per_x2]).T),
                   np.ascontiguousarray(np.hstack([lam_mu, per_o, per_x2])))

    @staticmethod
    def terms(x: np.ndarray, obs: np.ndarray | None = None) -> np.ndarray:
        """(n, 3F) [o x, o, o x^2]: the left factor of the fused product (NaN-free)."""
        if obs is None:
            return np.hstack([x, np.ones_like(x), x * x])
        xo = np.where(obs, x, 0.0)
        return np.hstack([xo, obs.astype(np.float64), xo * xo])

    def loglik_at(self, v: np.ndarray, s: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """ell of K (stream, flat state) pairs: v (n, 3F) from ``terms``; s, rows (K,).  Returns (K,).
        The same sums as ``loglik`` for only the states asked for (the live ones of a filter)."""
        if v.shape[0] == 1:
            return self.fused_t[rows] @ v[0]
        return np.einsum("kf,kf->k", self.fused_t[rows], v[s])

    def loglik(self, x: np.ndarray, obs: np.ndarray | None = None) -> np.ndarray:
        """x: (n, F) features (NaN allowed where unobserved); obs: (n, F) bool or None (all).

        Returns (n, C, M) expected log-likelihoods of the observed entries of each row.
        """
        return (self.terms(x, obs) @ self.fused).reshape(x.shape[0], self.C, self.M)
