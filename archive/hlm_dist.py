"""HLM training with the E-step's per-sequence work on Dask workers.

Of one variational sweep (``hlm.train.VariationalEM.e_step``), Q(Z) and Q(l) need every
sequence's statistics but cost little; Q(pi) (eqs. 7/10: the emissions of every frame under
every latent state, then forward-backward) is per sequence and is almost all the time.
``DaskEStep`` runs ``hlm.train.pi_stats`` on chunks of sequences, one task per chunk, and
stacks the statistics back in sequence order; the process driving EM then reduces them
(W = psi^T Gs, R = sum_k psi_k GX_k, the bound) with the same code and in the same order as
one process does, so the bound and parameters agree with single-process training to
the last bit: every chunk is padded to the longest sequence of all, as one process pads them,
so every BLAS product has the shapes it has in one process (with chunks padded only to their own
longest sequence the products' blocking changed, the last bits differed, and after four EM
iterations the parameters differed by 2e-8 relative: EM amplifies rounding).  Tested to 1e-9.

The frames are scattered to the workers once per EM run (each chunk to one worker, where its
tasks then run); each E-step sends only the current tables, (K, F + 1, M) numbers, and gets
back (K, M, F) statistics.  Missing values (eq. 18 refills them every M-step) change the frames,
so with gaps the chunk's frames go with every task instead.
"""
from __future__ import annotations

import contextlib
import weakref
from collections.abc import Iterator

import numpy as np

from hlm.train import estep_map, pi_stats

# chunks per worker: more than one evens out chunks of unequal cost
CHUNKS_PER_WORKER = 1


def _chunk_task(X: np.ndarray, lengths: np.ndarray, Baug: np.ndarray, plam: np.ndarray, log_d: np.ndarray,
                want_G: bool) -> dict:
    import time

    from archive.worker import tune_malloc

    tune_malloc()  # the nanny's MALLOC_TRIM_THRESHOLD_ doubled this task's CPU (archive/worker.py)
    # one BLAS thread: a Dask worker's nanny sets OPENBLAS_NUM_THREADS=1 (pre-spawn-environ)
    t0 = time.perf_counter()
    st = pi_stats(X, lengths, Baug, plam, log_d)
    if not want_G:
        st["G"] = None
    st["compute_s"] = time.perf_counter() - t0   # the task's own time, for DaskEStep.timings
    return st


def partition(n_sequences: int, n_chunks: int) -> list[np.ndarray]:
    """Sequence indices 0..K-1 in ``n_chunks`` contiguous groups of (nearly) equal size.  Every
    chunk is padded to the longest sequence of all (``DaskEStep._layout``), so a chunk costs in
    proportion to its number of sequences."""
    return [g for g in np.array_split(np.arange(n_sequences), max(1, min(n_chunks, n_sequences))) if g.size]


class DaskEStep:
    """A mapper for ``hlm.train.estep_map``: Q(pi) of every sequence on the client's workers."""

    def __init__(self, client, n_chunks: int | None = None):
        self.client = client
        self.n_chunks = n_chunks or CHUNKS_PER_WORKER * max(1, len(client.nthreads()))
        self._runs: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
        self.calls = 0
        # per call: (wall seconds of the call, its longest task's compute seconds); the difference is
        # what the cluster adds (sending the tables, scheduling, results back, stacking them)
        self.timings: list[tuple[float, float]] = []

    def _layout(self, em) -> list[tuple[np.ndarray, int, object]]:
        """Per chunk: (sequence indices, T_max of the chunk, scattered frames or None)."""
        if em not in self._runs:
            groups = partition(em.K, self.n_chunks)
            # every chunk padded to the longest sequence of all, as one process pads them: the same
            # shapes give the same BLAS blocking and summation order, so the same bits
            Ts = [int(em.X.shape[0])] * len(groups)
            refs: list = [None] * len(groups)
            if not em.has_missing:  # one scatter call spreads the chunks over the workers
                refs = self.client.scatter([np.ascontiguousarray(em.X[:T, idx]) for idx, T in zip(groups, Ts)],
                                           hash=False)
            self._runs[em] = list(zip(groups, Ts, refs))
        return self._runs[em]

    def __call__(self, em, Baug: np.ndarray, plam: np.ndarray, log_d: np.ndarray) -> dict:
        import time

        self.calls += 1
        t0 = time.perf_counter()
        chunks = self._layout(em)
        futures = []
        for idx, T, ref in chunks:
            X = ref if ref is not None else np.ascontiguousarray(em.X[:T, idx])
            futures.append(self.client.submit(_chunk_task, X, em.lengths[idx], Baug[idx], plam[idx], log_d[idx],
                                              em.has_missing, pure=False, retries=2))
        parts = self.client.gather(futures)
        K, M = em.K, em.M
        out = {"jumps": np.empty((K, log_d.shape[1])), "log_z": np.empty(K), "GX": np.empty((K, M, em.F)),
               "Gs": np.empty((K, M)), "H_pi": np.empty(K), "G": None}
        if em.has_missing:
            out["G"] = np.zeros((em.X.shape[0], K, M))
        for (idx, T, _), st in zip(chunks, parts):
            for k in ("jumps", "log_z", "GX", "Gs", "H_pi"):
                out[k][idx] = st[k]
            if em.has_missing:
                out["G"][:T, idx] = st["G"]
        self.timings.append((time.perf_counter() - t0, max(st["compute_s"] for st in parts)))
        return out


@contextlib.contextmanager
def distributed_estep(client, n_chunks: int | None = None) -> Iterator[DaskEStep]:
    """Every HLM fit inside the block runs its E-step on ``client``'s workers."""
    mapper = DaskEStep(client, n_chunks)
    with estep_map(mapper):
        yield mapper
