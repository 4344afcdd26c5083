"""Where batch work runs: a Dask cluster (``dask.distributed``).

* ``--scheduler tcp://HOST:PORT``: an existing cluster (``dask scheduler`` and ``dask worker``
  processes, a render farm's, a Kubernetes or SLURM deployment's).
* otherwise a ``LocalCluster`` of worker processes on this machine, one thread each (the work
  is numpy and numba under the GIL), ``--workers N`` of them (default: one per CPU).

Workers import lacuna from the same environment as the client; nothing is installed on them.
"""
from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

from lacuna.errors import LacunaError

# seconds to wait for an existing scheduler to answer and for workers to join
CONNECT_TIMEOUT_S = 30
WORKERS_TIMEOUT_S = 120


def default_workers() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def open_client(scheduler: str | None = None, workers: int | None = None, quiet: bool = True) -> Iterator:
    """A connected ``distributed.Client``; a local cluster is started (and stopped after) when
    no scheduler address is given.  LacunaError when the scheduler cannot be reached."""
    import logging

    from distributed import Client, LocalCluster

    if workers is not None and workers < 1:
        raise LacunaError(f"--workers must be >= 1 (got {workers})")
    if quiet:
        for name in ("distributed", "distributed.nanny", "distributed.scheduler", "distributed.worker"):
            logging.getLogger(name).setLevel(logging.ERROR)
    if scheduler:
        if workers is not None:
            raise LacunaError("--workers sizes a local cluster; an existing cluster (--scheduler) has its own workers")
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError) as e:
            raise LacunaError(f"--scheduler {scheduler}: cannot connect ({e})") from None
        try:
            client.wait_for_workers(1, timeout=WORKERS_TIMEOUT_S)
            yield client
        finally:
            client.close()
        return
    n = workers or default_workers()
    # BLAS and numba threads: one per worker process, the processes are the parallelism
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from archive.worker import THREAD_VARS

    # every thread pool in a worker at 1 (BLAS, OpenMP, numba's parallel layer): n workers on n cores
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                           silence_logs=logging.ERROR if quiet else logging.WARNING, env={k: "1" for k in THREAD_VARS})
    try:
        client = Client(cluster)
        try:
            client.wait_for_workers(n, timeout=WORKERS_TIMEOUT_S)
            client.run(_own_session)  # each worker its own share of the CPU (see _own_session)
            yield client
        finally:
            client.close()
    finally:
        cluster.close()


def _own_session() -> bool:
    """Make this worker process the leader of a session of its own (True if it now is).

    With the kernel's autogroup scheduling (``/proc/sys/kernel/sched_autogroup_enabled``, on by
    default on desktop and many server kernels) the CPU is shared fairly between *sessions*: the
    local cluster's workers, children of the caller, shared the caller's one session's share, and
    two of them got about 0.46 of a CPU each on two busy cores where one alone got 0.78
    (docs/ARCHIVE.md).  Workers of a cluster started by hand (``dask worker``) are in sessions of
    their own already."""
    try:
        if os.getsid(0) != os.getpid():
            os.setsid()
        return os.getsid(0) == os.getpid()
    except OSError:
        return False


def describe(client) -> dict:
    """Scheduler address and workers (address -> threads) of a client's cluster."""
    nt = client.nthreads()
    return {"scheduler": client.scheduler.address, "workers": len(nt), "threads": int(sum(nt.values()))}
