"""The loop's wait between two turns: how long to poll, and what the loop does before it sleeps.

``Waiting`` is a part of :class:`daemon.loop.Daemon` (daemon/parts.py).  :meth:`Waiting._wait`
polls at once when frames are waiting to be served, else up to IDLE_POLL_MS (sooner when the
systemd watchdog is due); shortly before a stream's next frame is due it rehearses that frame's
path (daemon/prewarm.py), and what landed meanwhile is given the rehearsal's start as its
receipt time; for ``busy_poll_ms`` after a message it polls without sleeping
(:meth:`Waiting._spin`); after a rehearsal it spins up to ``prewarm_spin_ms`` for the frame it
warmed for (:meth:`Waiting._spin_until`, bench/notebook/spin-38.md).  Each wait is timed for
daemon/stalls.py.
"""
from __future__ import annotations

import os
import time
from typing import Any

from daemon import wire
from daemon.parts import Parts

IDLE_POLL_MS = 100  # poll timeout when nothing is pending (signal flags are read at least this often)


class Waiting(Parts):
    """The loop's wait (mixed into :class:`daemon.loop.Daemon`)."""

    @property
    def _busy_s(self) -> float:
        return self.cfg.busy_poll_ms / 1000.0   # read each time: a reload may change it

    def _wait(self) -> tuple[dict[Any, int], float | None]:
        """Until something arrives or the loop has work: the poll's answer (empty: nothing came)
        and the receipt time to give all it found (:meth:`daemon.loop.Daemon.turn`'s
        ``arrived``), or None: each message is stamped as it is read."""
        pending = bool(self.sessions.waiting or self.sessions.blocks)  # (cost: the streams with a frame, not the open ones)
        timeout = 0 if pending else IDLE_POLL_MS
        wd = self.notify.watchdog_due(time.monotonic())
        if wd is not None:
            timeout = min(timeout, max(0, int(wd * 1000)))
        pw = self.prewarm
        rehearsed: float | None = None  # perf_counter just before a rehearsal began
        if timeout and pw.due is not None:
            # the next frame is due soon: warm the path it takes (daemon/prewarm.py); the
            # poll's timeout is whole milliseconds, so this runs lead to lead + 1 ms ahead
            t = time.perf_counter()
            left = pw.due - t
            if left < 0.001:
                pw.rehearse(self.sessions.sessions, self.sched, wire.encode)
                rehearsed = t
            else:
                timeout = min(timeout, int(left * 1000))
        self.stalls.sleeping()
        due = time.perf_counter() + timeout / 1000.0
        if rehearsed is not None and (ready := self.net.poll(0)):  # type: ignore[union-attr]
            # what landed while the rehearsal ran waited for it to finish: it is stamped with the
            # rehearsal's start, not when read, so its proc_us and the latency in `status` show
            # that wait.  For a message that landed during the rehearsal (or is read with those
            # that did) that is an upper bound on its wait; one that landed before it, during the
            # turn before, is stamped late by that much, as any message landing in a turn is
            self.stalls.woke(due)
            self._last_rx = time.perf_counter()
            return ready, rehearsed
        if rehearsed is not None and timeout and (spin := self._pre_spin_s):
            # (prewarm_spin_ms) the frame the rehearsal warmed for is due within ~1 ms: wait for it
            # spinning, so it lands on a core that did not halt and is read at once, instead of
            # after the kernel wakes this thread; then sleep in poll as usual
            t = time.perf_counter()
            ready = self._spin_until(t + spin)
            pw.spun(bool(ready), time.perf_counter() - t)
            if ready or self.flag_stop or self.flag_reload:
                self.stalls.woke(due)
                if ready:
                    self._last_rx = time.perf_counter()
                return ready, None
        if timeout and self._busy_s:
            due += max(0.0, self._last_rx + self._busy_s - time.perf_counter())
            ready = self._spin(timeout)
        else:
            ready = self.net.poll(timeout)  # type: ignore[union-attr]
        self.stalls.woke(due)
        if ready:
            self._last_rx = time.perf_counter()
        return ready, None

    @property
    def _pre_spin_s(self) -> float:
        # (not under SCHED_RR: a spinning real-time thread keeps the kernel's own network work off
        # its core, which is why busy_poll_ms is refused with realtime_priority)
        if self.cfg.realtime_priority is not None:
            return 0.0
        return self.cfg.prewarm_spin_ms / 1000.0   # read each time: a reload may change it

    def _spin_until(self, end: float) -> dict[Any, Any]:
        """Poll without sleeping until something is ready, a stop or reload is asked for, or
        ``end`` (perf_counter); an empty answer once ``end`` passed with nothing ready."""
        net = self.net
        while True:
            ready = net.poll(0)  # type: ignore[union-attr]
            if ready or self.flag_stop or self.flag_reload or time.perf_counter() >= end:
                return ready
            os.sched_yield()  # let ZeroMQ's I/O thread, which moves the bytes, run on this core at once

    def _spin(self, timeout_ms: int) -> dict[Any, Any]:
        """Busy-poll (``busy_poll_ms``): for that long after the last message arrived, poll without
        sleeping, so the next frame is picked up as soon as it lands instead of after the kernel
        wakes the thread (0.3-1 ms on a virtual machine, most of a loopback round trip).  Costs a
        core while frames flow; once the stream pauses for longer, sleep in poll as usual."""
        end = self._last_rx + self._busy_s
        if time.perf_counter() < end:
            ready = self._spin_until(end)
            if ready or self.flag_stop or self.flag_reload:
                return ready
        return self.net.poll(timeout_ms)  # type: ignore[union-attr]
