"""What HLM training produces: the learned parameters and the record of a fit."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class HLMParams:
    """Learned quantities, in feature space.  C styles, M phases, F features, J jumps, K sequences.

    zbar : (M, F) parent cycle.  mu, var : (C, M, F) mean and variance of Q(Z^c).
    lam : (C, F) style noise precisions Lambda^c.  tau : (C,).  d : (K, J) per training sequence.
    lam_s, lam_zbar : scalars.
    """

    zbar: np.ndarray
    mu: np.ndarray
    var: np.ndarray
    lam: np.ndarray
    tau: np.ndarray
    d: np.ndarray
    lam_s: float
    lam_zbar: float

    @property
    def n_styles(self) -> int:
        return self.mu.shape[0]

    @property
    def n_states(self) -> int:
        return self.mu.shape[1]

    @property
    def n_jumps(self) -> int:
        return self.d.shape[1]

    def d_population(self) -> np.ndarray:
        """(J,) transition probabilities for a new sequence: the mean of the training d^k."""
        d = self.d.mean(0)
        return d / d.sum()


@dataclass
class FitResult:
    params: HLMParams
    psi: np.ndarray            # (K, C) style posteriors of the training sequences
    bounds: list[float]        # bound after each EM iteration of the kept run
    restart_bounds: list[float]  # bound of every restart at the end of its screening iterations
    seed: int
    seconds: float
    filled: list[np.ndarray] = field(default_factory=list)  # training sequences with (18) fills


class BoundWarning(RuntimeWarning):
    """The variational bound went down (it should not)."""
