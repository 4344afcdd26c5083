"""Control requests on the serving side: ``status``, ``list-models``, ``reset``, ``release``,
``reload`` (the client is daemon/server.py's ``control``), and the status map itself."""
from __future__ import annotations

import os
import time
from typing import Any

from daemon import wire
from daemon.parts import Parts
from daemon.session import Origin, SessionError, principal

STATUS_STREAMS = 256  # streams `status` details by default, most recently active first (`limit` asks for more)


class Control(Parts):
    """(mixed into :class:`daemon.loop.Daemon`)"""

    # ---- control ----------------------------------------------------------------------------
    def _control(self, msg: wire.Control, origin: Origin) -> None:
        if msg.cmd == "status":
            if msg.stream is not None and msg.stream not in self.sessions.sessions:
                self._out.append((origin, wire.ControlReply("status", False, {}, f"no open stream {msg.stream!r}")))
                return
            n = STATUS_STREAMS if msg.limit is None else msg.limit
            if n > STATUS_STREAMS and not self.budget.allow(principal(origin), self.clock(), (n - STATUS_STREAMS) / 64.0):
                self._rate_limited(origin)  # (a long listing costs its length)
                return
            self._out.append((origin, wire.ControlReply("status", True, self.status(n, msg.stream))))
        elif msg.cmd == "list-models":
            self._out.append((origin, wire.ControlReply("list-models", True, {"models": {n: m.info() for n, m in self.models.items()},
                                                                         "default": self.cfg.default_model})))
        elif msg.cmd == "reset":
            assert msg.stream is not None
            ok, orphans = self.sessions.reset(msg.stream, principal(origin), self._operator(origin))
            for o, m in orphans:
                self._out.append((o, m))
            self.log("info", "stream_reset", stream=msg.stream, existed=ok)
            self._out.append((origin, wire.ControlReply("reset", ok, {"stream": msg.stream},
                                                 None if ok else f"no open stream {msg.stream!r}")))
        elif msg.cmd == "release":
            assert msg.stream is not None
            ok = self.sessions.release(msg.stream, principal(origin))
            self._out.append((origin, wire.ControlReply("release", ok, {"stream": msg.stream},
                                                 None if ok else f"no open stream {msg.stream!r}")))
        elif msg.cmd == "reload":
            if not self._operator(origin):
                raise SessionError("not_operator", "reload needs an operator (with CURVE: a key listed in "
                                                   "security.operator_keys; SIGHUP reloads too)")
            self._start_reload(origin)

    def _operator(self, origin: Origin) -> bool:
        """May this peer reload and reset others' streams (daemon/transport.py, ``operator``)?"""
        return self.net.operator(origin) if self.net is not None else True

    def status(self, limit: int = STATUS_STREAMS, stream: str | None = None) -> dict[str, Any]:
        """The status map; per-stream detail for the ``limit`` most recently active streams (or
        for ``stream`` alone): its cost does not grow with the idle streams."""
        ss = self.sessions
        listed = [stream] if stream is not None else ss.most_recent(limit)
        return {
            "pid": os.getpid(), "uptime_s": round(time.time() - self.started, 3), "config": self.cfg.path,
            "budget_ms": self.cfg.budget_ms, "overdue": self.cfg.overdue, "default_model": self.cfg.default_model,
            "models": {n: m.info() for n, m in self.models.items()},
            "latency": self.metrics.latency_summary(), "step": self.metrics.step_summary(),
            "counters": dict(self.metrics.counters), "rejected": dict(self.metrics.rejected),
            "streams": {sid: ss.sessions[sid].info() for sid in listed},
            "streams_total": len(ss.sessions), "streams_listed": len(listed),
            "expired": self.sessions.expired, "takeovers": self.sessions.takeovers, "step_errors": self.sched.step_errors, "probes": self.sched.probes,
            "last_step_error": self.sched.last_error, "reload": self.last_reload,
            "security": self.net.guard.info() if self.net is not None and self.net.guard is not None else None,
            "cpu_latency": self.qos.info(), "realtime": self.rt.info(), "prewarm": self.prewarm.info(),
            "metrics_http": self.http.info() if self.http is not None else None,
            "loop": self.stalls.info(),
        }

    def _status_line(self) -> str:
        lat = self.metrics.latency_summary()
        p99 = lat.get("p99_ms")
        return (f"{len(self.sessions.sessions)} streams, {self.metrics.counters.get('frames_out', 0)} frames out, "
                f"p99 {p99 if p99 is not None else '-'} ms, models: {', '.join(self.models)}")

