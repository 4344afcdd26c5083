"""Precomputed tables of the online HLM filter (``hlm.online``), one set per model."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hlm.emissions import EmissionTables


@dataclass
class FilterTables:
    """Everything the per-frame step reads, precomputed once per model.  Shapes: C styles,
    M phases, F features, J jumps."""

    em: EmissionTables
    mu: np.ndarray        # (C*M, F)
    q2: np.ndarray        # (C*M, F) mu^2 + var + 1/lam: second moment of x given (c, m)
    log_prior: np.ndarray  # (C, M) log tau_c - log M
    d_pop: np.ndarray     # (J,)
    cos: np.ndarray       # (M,) cos(2 pi m / M)
    sin: np.ndarray
    adapt_rate: float = 0.0
    prior_strength: float = 240.0
    kappa: float = 0.0     # stream-cycle adaptation pseudo-count (frames); 0 = off
    width: int = 5         # knots of that adaptation are 2 width + 1 states apart
    kappa_global: float = 0.0  # pseudo-count of the stream's constant offset (0 = knots only)
    style_switch: float = 0.0  # probability per frame of a change of style (0 = the paper's one style)
    var: np.ndarray | None = None   # (C*M, F) Q(Z) variances, for the adapted second moment
    inv_lam: np.ndarray | None = None  # (C, F)
    style_of: np.ndarray | None = None  # (C*M,) style index of each flat state
    pack: np.ndarray | None = None      # (C*M, 4F) [lam mu | lam | mu | q2] per state, for fill
    lam_rows: np.ndarray | None = None  # (C*M, F) lam of each state's style
    var_q: np.ndarray | None = None     # (C*M, F) var + 1/lam

    @classmethod
    def build(cls, mu: np.ndarray, var: np.ndarray, lam: np.ndarray, tau: np.ndarray, d_pop: np.ndarray,
              adapt_rate: float = 0.0, prior_strength: float = 240.0, kappa: float = 0.0,
              width: int = 5, kappa_global: float = 0.0, style_switch: float = 0.0) -> FilterTables:
        C, M, F = mu.shape
        ang = 2.0 * np.pi * np.arange(M) / M
        with np.errstate(divide="ignore"):  # a style with tau = 0 is impossible: log 0 = -inf
            lp = np.log(tau)[:, None] - np.log(M) + np.zeros((C, M))
        return cls(EmissionTables.build(mu, var, lam), np.ascontiguousarray(mu.reshape(C * M, F)),
                   np.ascontiguousarray((mu ** 2 + var + 1.0 / lam[:, None, :]).reshape(C * M, F)),
                   lp, np.asarray(d_pop, dtype=np.float64), np.cos(ang), np.sin(ang), float(adapt_rate),
                   float(prior_strength), float(kappa), int(width), float(kappa_global), float(style_switch),
                   np.ascontiguousarray(var.reshape(C * M, F)),
                   1.0 / lam, np.repeat(np.arange(C), M))

    def __post_init__(self) -> None:
        C, M = self.em.C, self.em.M
        # stream-cycle knots: state m sits at u = m nb / M between knots floor(u) and floor(u) + 1
        nb = max(3, int(round(M / (2 * self.width + 1)))) if self.width > 0 else M
        u = np.arange(M) * nb / M
        b0 = np.floor(u).astype(int)
        self.n_bins = nb
        self.bin0 = (np.arange(C)[:, None] * nb + b0[None]).ravel()
        self.bin1 = (np.arange(C)[:, None] * nb + (b0[None] + 1) % nb).ravel()
        self.bin_a = np.tile(u - b0, C)
        # (C M, C n_bins): state m's weights 1 - a and a on its two knots (dense, for a lone stream)
        kw = np.zeros((C * M, C * nb))
        np.add.at(kw, (np.arange(C * M), self.bin0), 1.0 - self.bin_a)
        np.add.at(kw, (np.arange(C * M), self.bin1), self.bin_a)
        self.knot_weights = kw
        self.lam_rows = np.ascontiguousarray(np.repeat(self.em.lam, M, axis=0))
        self.var_q = np.ascontiguousarray(self.var + np.repeat(self.inv_lam, M, axis=0))
        self.pack = np.ascontiguousarray(np.hstack([self.em.lam_mu, self.lam_rows, self.mu, self.q2]))
        # the emission's terms that do not involve x or the mean: 1/2 log(lam / 2 pi) - lam var / 2
        self.emit_a = np.ascontiguousarray(np.repeat(self.em.log_norm, M, axis=0) - 0.5 * self.lam_rows * self.var)
        self.emit_pack = np.ascontiguousarray(np.hstack([self.mu, 0.5 * self.lam_rows, self.emit_a]))
        self.prior_flat = np.exp(self.log_prior).reshape(-1)   # (C M,) the first frame's prediction
        # the features of the "ll" row's second, partial normaliser (columns 2-3: ``hlm.online.init_state``);
        # none (the columns stay 0, no extra work) unless the model's owner asks (HLMModel.set_ll_feats)
        self.ll_feats = np.zeros(0, np.int64)

    @property
    def shape(self) -> tuple[int, int]:
        return self.em.C, self.em.M
