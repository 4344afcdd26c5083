"""A pooled-chain ensemble of CRBMs: several CRBMs trained from different seeds fill one stream
together.

Per frame every member runs its own S clamped-Gibbs chains (``crbm.filler``) from the SAME
history (the ensemble's completed past frames); the fill is the mean of all members' chains and
the std pools the within-member spread with the spread between members.  The completed (mean)
frame becomes everyone's history, so the members cannot drift apart over a long gap: this is
not the same as averaging fills that each member produced alone (tried, did not help,
docs/BENCHMARKS.md ## CRBM).  Why it helps: a single CRBM's 63-frame free-running fill
compounds its own idiosyncratic errors, which vary by +-20% with the training seed; averaging
the members' one-step predictions cancels the part of those errors that is seed noise.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from crbm.filler import CRBMModel, Knobs
from crbm.model import CRBM
from mocap.representation import Representation

# member i samples with seed + _SEED_STRIDE * i: distinct, reproducible streams per member
_SEED_STRIDE = 1_000_003


class CRBMEnsemble(CRBMModel):
    """CRBMModel over M first-level CRBMs sharing one representation (no second level).

    Parameters
    ----------
    representation : the fitted feature space.
    members : M trained CRBMs of equal order and visible width (hidden sizes may differ).
    n_gibbs, n_chains, mode, init_noise, seed, meta : as CRBMModel; ``n_chains`` is per member,
        so a frame runs M * n_chains chains.
    """

    method = "crbm-ens"

    def __init__(self, representation: Representation, members: Sequence[CRBM], n_gibbs: int = 30,
                 n_chains: int = 1, mode: str = "gibbs", init_noise: float = 0.01, seed: int = 0,
                 meta: dict[str, Any] | None = None, bias_rate: float = 0.0, final_step: str = "last"):
        members = list(members)
        if not members:
            raise ValueError("an ensemble needs at least one CRBM")
        orders = {m.order for m in members}
        if len(orders) != 1:
            raise ValueError(f"ensemble members must share one order (got {sorted(orders)})")
        self._members = [CRBMModel(representation, m, None, n_gibbs=n_gibbs, n_chains=n_chains, mode=mode,
                                   init_noise=init_noise, seed=seed, final_step=final_step) for m in members]
        # bias_rate (``CRBMModel``) acts on the pooled fill, against the members' mean prediction
        super().__init__(representation, members[0], None, n_gibbs=n_gibbs, n_chains=n_chains, mode=mode,
                         init_noise=init_noise, seed=seed, meta=meta, bias_rate=bias_rate, final_step=final_step)

    @property
    def members(self) -> list[CRBM]:
        return [m.crbm for m in self._members]

    def info(self) -> dict[str, Any]:
        d = super().info()
        d.update(members=len(self._members))
        return d

    def _one_step_prediction(self, hist: np.ndarray) -> np.ndarray:
        """The members' mean one-step prediction: the ensemble's own, for the bias adaptation."""
        return np.mean([mm._one_step_prediction(hist) for mm in self._members], 0)

    def _fill_rows(self, state: dict[str, np.ndarray], rows: np.ndarray, zc: np.ndarray,
                   obs: np.ndarray, kn: Knobs) -> tuple[np.ndarray, np.ndarray]:
        """Every member fills from the shared history; mean of the members' chain means (equal
        S each, so the mean of all chains) and pooled variance (within + between members)."""
        means, variances = [], []
        for i, mm in enumerate(self._members):
            # the step's knobs are the ensemble's, handed down; member i samples with its own
            # seed (the members' own knobs are never read or written)
            f, s = mm._fill_rows(state, rows, zc, obs, kn._replace(seed=kn.seed + _SEED_STRIDE * i))
            means.append(f)
            variances.append(s * s)
        M = np.stack(means)
        fill = M.mean(0)
        var = np.stack(variances).mean(0) + M.var(0)
        return fill, np.where(obs, 0.0, np.sqrt(var))

    # ---- the model file: member i's arrays as m{i}_W, m{i}_A, ... (crbm/persist.py reads them)
    def _file_meta(self) -> dict[str, Any]:
        meta = super()._file_meta()
        meta["hyperparameters"] = {"members": [{**m.hyperparameters(), "n_epochs_done": m.n_epochs_done_}
                                               for m in self.members]}
        return meta

    def _file_arrays(self) -> dict[str, np.ndarray]:
        arrays: dict[str, np.ndarray] = {}
        for i, m in enumerate(self.members):
            arrays.update(m.get_arrays(f"m{i}_"))
        return arrays
