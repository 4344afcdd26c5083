"""Reloads: the daemon's side (its worker thread and queue are daemon/reloader.py).

A reload reads the config and model files and checks the models on a helper thread while the
main loop keeps serving; the loop swaps the result in between two ticks.  The worker's promises
(no thread started at reload time; every request answered by a reload that started after it;
every exception a refused reload naming its cause) are daemon/reloader.py's.
"""
from __future__ import annotations

import sys
import time

from daemon import config as config_mod
from daemon import wire
from daemon.log import Log
from daemon.models import Loaded, load_all
from daemon.parts import Parts
from daemon.realtime import ordinary
from daemon.reloader import Result
from daemon.session import Origin

RELOAD_SWITCH_S = 0.0005  # sys.setswitchinterval while a reload thread runs (see _reload_started)


class Reloading(Parts):
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
        except Exception as e:  # noqa: BLE001 - an escaped exception would leave the reload unanswered and unlogged
            return None, old, {"config": f"{path}: {type(e).__name__}: {e}"[:500]}
        try:
            table, errors = load_all(new_cfg, old)
        except Exception as e:  # noqa: BLE001 - same: refuse the reload, keep the old models, say why
            return None, old, {"models": f"{type(e).__name__}: {e}"[:500]}
        return new_cfg, table, errors

    def _finish_reload(self, result: Result, waiters: list[Origin]) -> None:
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

