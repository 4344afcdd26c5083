"""Keep BLAS single-threaded around small matrix products (CRBM training, the daemon's steps).

Mini-batch products (100 x 56 @ 56 x 150) are far too small to gain from threads; on a shared
2-core machine OpenBLAS threads spin against each other and training ran 20x slower (72 s
against 3.2 s for 50 epochs, measured).  threadpoolctl limits the pool for the duration of a
call.
"""
from __future__ import annotations

from contextlib import AbstractContextManager as ContextManager

from threadpoolctl import threadpool_limits as _limits


def single_thread_blas() -> ContextManager[object]:
    """Limit BLAS to one thread for the duration of a ``with`` block."""
    return _limits(limits=1, user_api="blas")


def limit_process_blas() -> object:
    """Limit BLAS to one thread for the rest of the process (the daemon: per-frame products of
    a few hundred multiply-adds, where a second BLAS thread made batched steps 7-20x slower on
    the shared two-core machine).  Keep the returned object alive."""
    return _limits(limits=1, user_api="blas")
