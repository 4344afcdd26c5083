"""Real-time CPU scheduling for the threads that serve frames (``daemon.realtime_priority``).

On a machine where other work competes for the CPUs (the capture software itself, a recorder,
a preview), the kernel's fair scheduler takes the CPU away from the daemon in the middle of a
tick: at 4x overload on the 2-core VM of docs/BENCHMARKS.md, the ticks whose frames overran the
4 ms budget had their thread on the CPU for only about 60% of the tick's wall time, 1-1.6 ms of
it lost to other processes, whatever the scheduler planned.  ``nice`` only changes the shares.
SCHED_RR puts a thread ahead of every ordinary (SCHED_OTHER) thread: it runs as soon as it is
runnable and keeps the CPU until it blocks, yields to a thread of equal or higher real-time
priority, or its round-robin slice ends.  This is what audio servers (PipeWire, JACK) and
capture software do.

Only the threads on a frame's path get it: the serving thread (the one that calls
:meth:`Realtime.request`) and ZeroMQ's I/O threads (``ZMQbg/IO/*``), which move the bytes to
and from the sockets.  The reload thread and the metrics HTTP thread stay ordinary: loading a
model must not compete with serving frames.  The kernel's real-time throttling (by default
95% of each second, ``/proc/sys/kernel/sched_rt_runtime_us``) keeps a runaway real-time thread
from freezing the machine.

Setting a real-time policy needs CAP_SYS_NICE or an RLIMIT_RTPRIO at least the priority asked
(``LimitRTPRIO=`` under systemd; see systemd/lacuna.service).  A request the daemon cannot make
is logged and shown in ``status``; the daemon serves on without it.
"""
from __future__ import annotations

import os
import threading
import time
from typing import Any

POLICY = os.SCHED_RR
IO_THREAD_PREFIX = "ZMQbg/IO"
IO_WAIT_S = 2.0  # for ZeroMQ's I/O threads to show up by name


def _comm(tid: int) -> str:
    try:
        with open(f"/proc/self/task/{tid}/comm") as f:
            return f.read().strip()
    except OSError:
        return ""


def io_threads() -> list[int]:
    """Thread ids of this process's ZeroMQ I/O threads."""
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return []
    return [t for t in tids if _comm(t).startswith(IO_THREAD_PREFIX)]


class Realtime:
    """SCHED_RR at ``priority`` for the calling thread and ZeroMQ's I/O threads, until
    :meth:`release` (or a request of None)."""

    def __init__(self) -> None:
        self.requested: int | None = None
        self.error: str | None = None
        self.threads: list[int] = []  # thread ids that hold the policy now

    @property
    def held(self) -> bool:
        return bool(self.threads)

    def request(self, priority: int | None, n_io: int = 1) -> bool:
        """Call from the serving thread, after the ZeroMQ context has its sockets (and so its
        ``n_io`` I/O threads).  Replaces any earlier request.  Returns whether it is held; on
        failure ``error`` says why and every thread is back to the ordinary policy."""
        self.release()
        self.requested, self.error = priority, None
        if priority is None:
            return False
        me = threading.get_native_id()
        # a new I/O thread names itself once it runs: give it a moment to
        io = io_threads()
        deadline = time.monotonic() + IO_WAIT_S
        while len(io) < n_io and time.monotonic() < deadline:
            time.sleep(0.005)
            io = io_threads()
        if len(io) < n_io:
            self.error = f"found {len(io)} of ZeroMQ's {n_io} I/O thread(s) (named {IO_THREAD_PREFIX}*)"
            return False
        done: list[int] = []
        for tid in [me, *io]:
            try:
                os.sched_setscheduler(tid, POLICY, os.sched_param(priority))
            except OSError as e:
                self.error = (f"cannot set SCHED_RR priority {priority} on thread {tid} "
                              f"({'the serving thread' if tid == me else _comm(tid)}): {e.strerror or e}")
                self.threads = done
                self.release()
                return False
            done.append(tid)
        self.threads = done
        return True

    def release(self) -> None:
        for tid in self.threads:
            try:
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
            except OSError:  # (a thread that ended; lowering one's own policy needs no privilege)
                pass
        self.threads = []

    def info(self) -> dict[str, Any]:
        policies = {}
        for tid in self.threads:
            try:
                policies[_comm(tid) or str(tid)] = {os.SCHED_RR: "rr", os.SCHED_FIFO: "fifo"}.get(
                    os.sched_getscheduler(tid), "other")
            except OSError:
                policies[str(tid)] = "gone"
        return {"requested_priority": self.requested, "held": self.held, "threads": policies, "error": self.error}


def ordinary() -> None:
    """Put the calling thread back on the ordinary policy (threads inherit their creator's:
    the reload thread calls this first)."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except OSError:
        pass
