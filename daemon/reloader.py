"""The reload worker: one thread started with the daemon, a queue of requests, one outcome each.

What a reload does with the daemon (read, check, swap in) is daemon/reload.py; this module is only
the thread and its queue, with these promises:

* **No thread is started at reload time.**  The worker is started once, with the daemon;
  under systemd's ``TasksMax`` a reload can never fail (or crash the daemon) for want of a
  thread.
* **Every request gets the outcome of a reload that started after it.**  A request (a
  ``reload`` control message, or SIGHUP) that arrives while a reload runs is queued for the
  next one; any number of them that arrive during one reload share that next reload (they are
  coalesced, never dropped, never answered with the outcome of a reload that began before
  they asked).
* The worker turns every exception into a refused reload naming the cause, so a reload can
  neither vanish unanswered nor end the worker.  Files are opened without blocking and must be
  regular files (daemon/safeopen.py), so a FIFO or a device at a config or model path cannot
  wedge the worker.
"""
from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

Result = tuple[Any, dict[str, Any], dict[str, str]]  # (new config or None, model table, {what: error})


class Reloader:
    """``request(waiter)`` from the main loop (waiter None: SIGHUP); ``poll()`` each turn returns
    ``(result, waiters)`` once the running reload finished, else None; then ``kick()`` starts
    the next one if requests are queued.  ``work()`` runs on the worker thread."""

    def __init__(self, work: Callable[[], Result], on_start: Callable[[], None] | None = None):
        self._work = work
        self._on_start = on_start or (lambda: None)
        self._go = threading.Event()
        self._lock = threading.Lock()
        self._result: Result | None = None
        self.running: list[Any] | None = None  # the waiters of the reload in progress
        self.queued: list[Any] | None = None  # requests for the next reload (None: none)
        self.started = 0  # reloads started so far; the running one is number `started`
        self._stopping = False
        self.thread = threading.Thread(target=self._run, name="reload", daemon=True)
        self.thread.start()

    @property
    def busy(self) -> bool:
        return self.running is not None

    def request(self, waiter: Any = None) -> None:
        if self.queued is None:
            self.queued = []
        if waiter is not None:
            self.queued.append(waiter)
        if self.running is None:
            self._start()

    def _start(self) -> None:
        self.running, self.queued = self.queued or [], None
        self.started += 1
        try:
            self._on_start()
        finally:  # (whatever the hook does, the reload runs and is answered)
            self._go.set()

    def poll(self) -> tuple[Result, list[Any]] | None:
        if self.running is None:
            return None
        with self._lock:
            res, self._result = self._result, None
        if res is None:
            return None
        waiters, self.running = self.running, None
        return res, waiters

    def kick(self) -> None:
        """After the caller installed what :meth:`poll` returned: start the reload that requests
        made while that one ran are queued for (it then starts from what was installed)."""
        if self.running is None and self.queued is not None:
            self._start()

    def stop(self) -> None:
        """End the worker (after the reload it may be running; it is a daemon thread anyway)."""
        self._stopping = True
        self._go.set()

    def _run(self) -> None:
        while True:
            self._go.wait()
            self._go.clear()
            if self._stopping:
                return
            try:
                res = self._work()
            except BaseException as e:  # noqa: BLE001 - the worker must never die
                res = (None, {}, {"reload": f"{type(e).__name__}: {e}"[:500]})
            with self._lock:
                self._result = res
