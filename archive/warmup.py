"""A Dask worker's start-up, run once as a task of its own before its first take
(``archive.batch.run_batch``): kept apart from archive/worker.py, which archive/fill.py imports,
so that this, which imports the fill, closes no import circle."""
from __future__ import annotations

from archive.worker import THREAD_VARS, tune_malloc


def warm(model_blob: tuple[str, bytes] | None = None) -> dict:
    """A worker's start-up work, done once before its first take: the malloc thresholds, the
    imports a fill needs (numpy, scipy, numba and the HLM: about 0.5 s on this VM) and the model
    (``archive.fill.model_from_bytes``).  ``archive.batch.run_batch`` runs it as one task per
    worker while it scans and submits the takes, so no take's timers carry it.  Returns its
    timers and the pid."""
    import os
    import time

    t0 = time.perf_counter()
    tune_malloc()
    import archive.fill  # noqa: F401  (the fill's imports: mocap, lacuna registry, numba via the models)
    import clients.replay  # noqa: F401
    import clients.takes  # noqa: F401
    import hlm.methods  # noqa: F401
    t1 = time.perf_counter()
    if model_blob is not None:
        from archive.fill import model_from_bytes

        model_from_bytes(*model_blob)
    # the thread pools a worker's numpy/numba may start: Dask's nanny sets the BLAS and OpenMP ones to 1
    # (distributed.nanny.pre-spawn-environ); the processes are the parallelism, so every one should be 1
    threads = {k: os.environ.get(k) for k in THREAD_VARS}
    return {"pid": os.getpid(), "imports_s": t1 - t0, "model_s": time.perf_counter() - t1, "threads": threads}
