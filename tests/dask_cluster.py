"""A real Dask cluster on loopback for the tests: ``dask scheduler`` and N ``dask worker``
processes (one thread each), started from this environment and torn down afterwards."""
from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass

from clients.configfile import free_port

CONNECT_TIMEOUT_S = 60      # scheduler up and answering
WORKERS_TIMEOUT_S = 120     # workers joined (imports under load take a while)
STOP_TIMEOUT_S = 20


@dataclass
class Cluster:
    address: str
    client: object
    scheduler: subprocess.Popen
    workers: list[subprocess.Popen]

    def worker_of_pid(self, pid: int) -> subprocess.Popen | None:
        """The ``dask worker`` process (the nanny) whose worker process has this pid."""
        ppids = self.client.run(os.getppid)          # worker address -> its nanny's pid
        pids = self.client.run(os.getpid)
        for addr, p in pids.items():
            if p == pid:
                return next((w for w in self.workers if w.pid == ppids[addr]), None)
        return None


def _stop(p: subprocess.Popen) -> None:
    if p.poll() is not None:
        return
    with contextlib.suppress(ProcessLookupError):
        os.killpg(p.pid, signal.SIGTERM)
    try:
        p.wait(STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGKILL)
        p.wait(STOP_TIMEOUT_S)


@contextlib.contextmanager
def dask_cluster(n_workers: int = 2, log_dir: str | None = None) -> Iterator[Cluster]:
    from distributed import Client

    dask = os.path.join(os.path.dirname(sys.executable), "dask")
    port = free_port()
    addr = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    procs: list[subprocess.Popen] = []
    client = None

    def spawn(args: list[str], name: str) -> subprocess.Popen:
        log = open(os.path.join(log_dir, f"{name}.log"), "wb") if log_dir else subprocess.DEVNULL
        p = subprocess.Popen([dask, *args], stdout=log, stderr=log, env=env, start_new_session=True)
        procs.append(p)
        return p

    try:
        sched = spawn(["scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"], "scheduler")
        workers = [spawn(["worker", addr, "--nworkers", "1", "--nthreads", "1", "--host", "127.0.0.1",
                          "--no-dashboard"], f"worker{i}") for i in range(n_workers)]
        client = Client(addr, timeout=CONNECT_TIMEOUT_S)
        client.wait_for_workers(n_workers, timeout=WORKERS_TIMEOUT_S)
        yield Cluster(addr, client, sched, workers)
    finally:
        if client is not None:
            client.close()
        for p in reversed(procs):
            _stop(p)
