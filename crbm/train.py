"""Train a CRBM filler from raw sequences: fit the representation, CD-1 on the first level,
optionally a second level on its hidden activities (section 6)."""
from __future__ import annotations

import contextlib
import contextvars
import datetime as _dt
import math
import sys
import time
from collections.abc import Sequence

import numpy as np

from crbm.ensemble import CRBMEnsemble
from crbm.filler import CRBMModel
from crbm.model import CRBM
from crbm.released import PAPER_TEXT, RELEASED  # noqa: F401  (PAPER_TEXT re-exported)
from mocap.representation import Representation

# The released demo: 2000 epochs of mini-batches of 100 on ~2600 frames, i.e. ~52k updates.
# Bigger training sets get fewer epochs so the number of updates (and the time) stays there.
DEMO_EPOCHS = 2000
DEMO_UPDATES = 52_000
MEMBER_SEED_STRIDE = 1000
# an ensemble's members train for this fraction of auto_epochs (1300 on taylor2007), so three fit
# the 120 s budget; measured on taylor2007, 1300 epochs beat 700 (docs/BENCHMARKS.md ## CRBM)
ENSEMBLE_EPOCH_FRACTION = 0.65


def auto_epochs(n_cases: int, batch_size: int = 100) -> int:
    per_epoch = max(1, math.ceil(n_cases / batch_size))
    return int(min(DEMO_EPOCHS, max(50, DEMO_UPDATES // per_epoch)))


def _progress_printer(what: str, every: int):
    t0 = time.perf_counter()

    def show(epoch: int, err: float) -> None:
        if epoch % every == 0 or epoch == 1:
            print(f"{what} epoch {epoch}: reconstruction error {err:.4f} per frame "
                  f"({time.perf_counter() - t0:.1f} s)", file=sys.stderr, flush=True)

    return show


# Who trains an ensemble's members: None = this process, one after another; else a mapper
# (Z, member indices, fit_member keywords) -> the fitted CRBMs in member order.
_MEMBER_MAP: contextvars.ContextVar = contextvars.ContextVar("crbm_member_map", default=None)


@contextlib.contextmanager
def member_map(mapper):
    """Train every ensemble's members inside the block through ``mapper`` (see ``_MEMBER_MAP``)."""
    token = _MEMBER_MAP.set(mapper)
    try:
        yield
    finally:
        _MEMBER_MAP.reset(token)


def fit_member(Z: Sequence[np.ndarray], i: int, *, hidden: int, order: int, epochs: int, history_noise: float,
               positive_hidden: str, average_last: float, seed: int, members: int, progress: bool,
               progress_every: int, bias_init_std: float = RELEASED["bias_init_std"],
               batches: str = RELEASED["batches"], dtype: str = RELEASED["dtype"]) -> CRBM:
    """CD-1 on the features Z for member i (seed ``seed + MEMBER_SEED_STRIDE * i``)."""
    what = "crbm" if members == 1 else f"crbm member {i + 1}/{members}"
    m = CRBM(n_hidden=hidden, order=order, n_epochs=epochs, history_noise=history_noise,
             positive_hidden=positive_hidden, bias_init_std=bias_init_std, batches=batches, dtype=dtype,
             average_last=average_last, random_state=seed + MEMBER_SEED_STRIDE * i,
             progress=_progress_printer(what, progress_every) if progress else None)
    return m.fit(Z)


def train_model(sequences: Sequence[np.ndarray], channels: Sequence[str], *, hidden: int = 150, order: int = 3,
                epochs: int | None = None, seed: int = 0, history_noise: float = RELEASED["history_noise"],
                positive_hidden: str = RELEASED["positive_hidden"], bias_init_std: float = RELEASED["bias_init_std"],
                batches: str = RELEASED["batches"], dtype: str = RELEASED["dtype"],
                average_last: float = 0.0, levels: int = 1, level2_hidden: int | None = None,
                level2_epochs: int | None = None, members: int = 1, n_gibbs: int = 30, n_chains: int = 1, mode: str = "gibbs",
                bias_rate: float = 0.0, final_step: str = "last",
                method: str | None = None, names: Sequence[str] = (), fps: float | None = None,
                root_mode: str = "relative", unwrap: bool = True, progress: bool = False, progress_every: int = 100,
                skeleton: str | None = None) -> CRBMModel:
    """sequences: raw (n_i, C) frames in ``channels``.  Returns a trained CRBMModel.

    ``epochs=None`` picks ``auto_epochs`` (2000 on the taylor2007 split, fewer on bigger sets).
    ``members > 1`` trains that many first-level CRBMs, member i from seed ``seed + MEMBER_SEED_STRIDE * i``
    (so member 0 is the single model of the same seed), each for ``epochs`` epochs (default
    ``ENSEMBLE_EPOCH_FRACTION`` of ``auto_epochs``), and returns a
    pooled-chain ``CRBMEnsemble`` (``crbm.ensemble``).
    """
    if isinstance(members, bool) or int(members) != members or members < 1:
        raise ValueError(f"members must be an integer >= 1 (got {members!r})")
    if members > 1 and levels != 1:
        raise ValueError("an ensemble (members > 1) has one level only")
    if levels not in (1, 2):
        raise ValueError(f"levels must be 1 or 2 (got {levels!r})")
    t0 = time.perf_counter()
    rep = Representation.fit(sequences, channels, root_mode=root_mode, unwrap=unwrap, normalize=True, skeleton=skeleton)
    Z = [rep.transform(s) for s in sequences]
    n_cases = sum(max(0, z.shape[0] - order) for z in Z)
    ep = auto_epochs(n_cases) if epochs is None else int(epochs)
    if epochs is None and members > 1:
        ep = max(50, int(round(ENSEMBLE_EPOCH_FRACTION * ep)))
    # members one after another: stacking them into batched (M, ...) matrix products was
    # tried and was slower with numpy here (6.5 s against 3 x 1.2 s for 30 epochs); the mapper
    # set with ``member_map`` (archive/crbm_dist.py) trains them on Dask workers instead
    kw = dict(hidden=hidden, order=order, epochs=ep, history_noise=history_noise, positive_hidden=positive_hidden,
              bias_init_std=bias_init_std, batches=batches, dtype=dtype, average_last=average_last, seed=seed,
              members=int(members), progress=progress, progress_every=progress_every)
    mapper = _MEMBER_MAP.get()
    fitted = ([fit_member(Z, i, **kw) for i in range(int(members))] if mapper is None
              else list(mapper(Z, list(range(int(members))), kw)))
    l1 = fitted[0]
    l2 = None
    if levels == 2:
        Hs = l1.hidden_probabilities(Z)
        ep2 = ep if level2_epochs is None else int(level2_epochs)
        l2 = CRBM(n_hidden=level2_hidden or hidden, order=order, n_epochs=ep2, visible="binary",
                  positive_hidden=positive_hidden, random_state=seed + 1,
                  progress=_progress_printer("crbm level 2", progress_every) if progress else None)
        l2.fit([h for h in Hs if h.shape[0] > order])
    seconds = time.perf_counter() - t0
    meta = {"training": {"data": list(names), "frames": int(sum(z.shape[0] for z in Z)), "fps": fps,
                         "seconds": round(seconds, 2), "epochs": ep,
                         "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
                         "reconstruction_error": l1.recon_errors_[-1] if l1.recon_errors_ else None}}
    if members > 1:
        meta["training"]["members"] = int(members)
        model = CRBMEnsemble(rep, fitted, n_gibbs=n_gibbs, n_chains=n_chains, mode=mode, seed=seed, meta=meta,
                             bias_rate=bias_rate, final_step=final_step)
        model.method = method or "crbm-ens"
        return model
    model = CRBMModel(rep, l1, l2, n_gibbs=n_gibbs, n_chains=n_chains, mode=mode, seed=seed, meta=meta,
                      bias_rate=bias_rate, final_step=final_step)
    model.method = method or ("crbm-2level" if levels == 2 else "crbm")
    return model
