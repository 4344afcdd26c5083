"""Reloads: one worker thread started with the daemon, a queue of requests, one outcome each.

A reload reads the config and model files and checks the models on a helper thread while the
main loop keeps serving; the loop swaps the result in between two ticks.  What this module
promises:

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

import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from daemon import config as config_mod
from daemon import wire
from daemon.log import Log
from daemon.models import Loaded, load_all
from daemon.realtime import ordinary
from daemon.session import Origin

RELOAD_SWITCH_S = 0.0005  # sys.setswitchinterval while a reload thread runs (see _reload_started)

Result = tuple[Any, dict, dict]  # (new config or None, model table, {what: error})


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


class Reloading:
    """The daemon's side of a reload: start, work (on the Reloader's thread), swap in
    (mixed into :class:`daemon.loop.Daemon`)."""

    # ---- reload -----------------------------------------------------------------------------
    def _start_reload(self, origin: Origin | None) -> None:
        """Queue a reload (daemon/reload.py): it starts now if none runs, else right after the
        one running, and ``origin`` (None: SIGHUP) gets the outcome of that later one."""
        self.reloader.request(origin)  # type: ignore[union-attr]

    def _reload_started(self) -> None:
        """(main thread, as a queued reload starts)"""
        self.notify.reloading()
        self.log("info", "reload_start", config=self.cfg.path, reload=self.reloader.started)  # type: ignore[union-attr]
        self._reload_args = (self.cfg.path, dict(self.models))
        # the reload thread holds the GIL while it loads and checks models; the serving thread,
        # wanting it, waits up to the switch interval (5 ms by default, over a 4 ms budget): ask
        # for a hand-over ten times as often while the reload runs
        self._switch = sys.getswitchinterval()
        sys.setswitchinterval(RELOAD_SWITCH_S)

    def _reload_work(self) -> tuple[config_mod.Config | None, dict[str, Loaded], dict[str, str]]:
        """(the reload thread) read the config and load what changed; never raises."""
        path, old = self._reload_args
        ordinary()  # (loading a model must not compete with serving frames)
        try:
            new_cfg = config_mod.load(path) if path else self.cfg
        except config_mod.ConfigError as e:
            return None, old, {"config": str(e)}
        except Exception as e:  # an escaped exception would leave the reload unanswered and unlogged
            return None, old, {"config": f"{path}: {type(e).__name__}: {e}"[:500]}
        try:
            table, errors = load_all(new_cfg, old)
        except Exception as e:  # same: refuse the reload, keep the old models, say why
            return None, old, {"models": f"{type(e).__name__}: {e}"[:500]}
        return new_cfg, table, errors

    def _finish_reload(self, result: tuple, waiters: list[Origin]) -> None:
        new_cfg, table, errors = result
        table = table or dict(self.models)  # (the worker's last resort keeps the models serving)
        sys.setswitchinterval(self._switch)
        if new_cfg is not None:
            moved = [k for k in ("zmq_router", "zmq_pull", "zmq_sub", "zmq_pub", "osc_listen", "metrics_http", "metrics_allow")
                     if getattr(new_cfg, k) != getattr(self.cfg, k)]
            if moved:
                self.log("warning", "reload_needs_restart", keys=moved, detail="socket addresses change only on restart")
            for k in moved:
                setattr(new_cfg, k, getattr(self.cfg, k))
            if new_cfg.default_model not in table:
                errors["config"] = f"default_model {new_cfg.default_model!r} did not load; keeping the old config"
                new_cfg = None
        if new_cfg is not None:
            self.cfg = new_cfg
            self.sched.budget_s = new_cfg.budget_ms / 1000.0
            self._drop_overdue = new_cfg.overdue == "drop"
            self.prewarm.lead_s = new_cfg.prewarm_ms / 1000.0
            self.sched.max_gap, self.sched.max_batch = new_cfg.max_gap_frames, new_cfg.max_batch
            self.sessions.max_streams = new_cfg.max_streams
            self.sessions.idle_s = new_cfg.idle_timeout_s
            self.log = Log(new_cfg.log_level, self.log.stream)
            self._request_cpu_latency()
            self._request_realtime()
            if self.net is not None and self.net.guard is not None:
                skipped = self.net.guard.reload(new_cfg.security)  # re-reads the authorized keys
                if skipped:
                    self.log("warning", "reload_needs_restart", keys=skipped, detail="key pairs change only on restart")
        self._install(table)
        ok = not errors
        n = self.reloader.started  # type: ignore[union-attr]
        self.last_reload = {"at": time.time(), "ok": ok, "errors": errors, "reload": n,
                            "models": {n: m.loaded_at for n, m in self.models.items()}}
        self.metrics.inc("reloads" if ok else "reload_failures")
        for name, err in errors.items():
            self.log("error", "reload_refused", model=name, error=err, detail="the old model keeps serving")
        self.log("info", "reload_done", always=True, ok=ok, models=list(self.models), reload=n, answered=len(waiters))
        self.notify.ready(self._status_line())
        for o in waiters:
            self._send(o, wire.ControlReply("reload", ok, {"models": {k: m.info() for k, m in self.models.items()},
                                                           "errors": errors, "reload": n},
                                            None if ok else "; ".join(f"{k}: {v}" for k, v in errors.items())))

