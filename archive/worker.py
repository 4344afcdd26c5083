"""Per-process set-up for work inside a Dask worker.

Dask's nanny starts workers with ``MALLOC_TRIM_THRESHOLD_=65536`` (``distributed.nanny.
pre-spawn-environ``) so that freed memory goes back to the system.  Setting that variable also
switches off glibc's dynamic mmap threshold, and the HLM's forward-backward allocates
temporaries of 50-500 KB at every frame: each one became a fresh mmap and munmap, with its page
faults, and the same E-step took 2-3x the CPU time in a worker that it takes in a plain process
(measured: 0.149 against 0.069 s CPU for one forward-backward of 600 frames x 12 sequences x 280
states).  ``tune_malloc`` restores large thresholds (``MALLOC_LIMIT_BYTES``) in the worker
process, once, before the first task's work: the E-step's CPU time then matched the plain
process's (0.079 s).
"""
from __future__ import annotations

import ctypes
import ctypes.util

# glibc mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
MALLOC_LIMIT_BYTES = 64 << 20     # heap kept / mmap threshold: a few of the E-step's temporaries
_done = False


def tune_malloc() -> bool:
    """Large trim and mmap thresholds for this process (glibc only; elsewhere nothing). Idempotent."""
    global _done
    if _done:
        return True
    _done = True
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(_M_TRIM_THRESHOLD, MALLOC_LIMIT_BYTES)) and bool(mallopt(_M_MMAP_THRESHOLD, MALLOC_LIMIT_BYTES))


THREAD_VARS = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS", "NUMBA_NUM_THREADS")
