"""Keep BLAS single-threaded around the CRBM's small matrix products.

Mini-batch products (100 x 56 @ 56 x 150) are far too small to gain from threads; on a shared
2-core machine OpenBLAS threads spin against each other and training ran 20x slower (72 s
against 3.2 s for 50 epochs, measured).  threadpoolctl limits the pool for the duration of a
call; without it this is a no-op (set OPENBLAS_NUM_THREADS=1 yourself).
"""
from __future__ import annotations

import contextlib
from typing import ContextManager

try:
    from threadpoolctl import threadpool_limits as _limits
except ImportError:  # pragma: no cover - optional dependency
    _limits = None


def single_thread_blas() -> ContextManager[object]:
    if _limits is None:
        return contextlib.nullcontext()
    return _limits(limits=1, user_api="blas")
