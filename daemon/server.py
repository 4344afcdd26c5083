"""`lacuna serve`: the main loop.

One thread serves everything: ``poll(timeout)`` over the ZeroMQ sockets and the OSC UDP socket,
drain what arrived (bounded), decode, hand frames to their sessions (conflating per stream),
one batched scheduler step per model, answer, then housekeeping against deadlines (watchdog,
idle expiry, metrics snapshot, signal flags).  Signal handlers only set flags.  A reload loads
and checks the new models on a helper thread and swaps them between two ticks, so no frame is
dropped or held up by the load; a file that fails keeps the old model and the log says why.
"""
from __future__ import annotations

import errno
import json
import os
import signal
import socket
import sys
import threading
import time
from typing import Any

import zmq

from daemon import config as config_mod
from daemon import osc, wire
from daemon.metrics import Metrics, MetricsHTTP
from daemon.models import Loaded, load_all
from daemon.notify import Notifier
from daemon.scheduler import Scheduler, fill_message
from daemon.session import Origin, Out, SessionError, SessionTable

DRAIN_MAX = 2048  # messages read per socket per tick: keeps one busy socket from starving the rest
IDLE_POLL_MS = 100  # poll timeout when nothing is pending (signal flags are read at least this often)
HOUSEKEEPING_S = 0.5
DRAIN_LINGER_MS = 1000  # on SIGTERM, let answers already queued reach their peers
UDP_MAX = 65535
ZMQ_MAXMSG_FLOOR = 1 << 20  # bytes
LEVELS = {"debug": 10, "info": 20, "warning": 30, "error": 40}


class Log:
    """JSON lines on stderr: {"ts", "level", "event", ...fields}."""

    def __init__(self, level: str = "info", stream: Any = None):
        self.level = LEVELS[level]
        self.stream = stream or sys.stderr

    def __call__(self, level: str, event: str, **fields: Any) -> None:
        if LEVELS[level] < self.level:
            return
        rec = {"ts": round(time.time(), 6), "level": level, "event": event, **fields}
        try:
            self.stream.write(json.dumps(rec, default=str) + "\n")
            self.stream.flush()
        except (OSError, ValueError):
            pass


class Daemon:
    def __init__(self, cfg: config_mod.Config, log: Log | None = None):
        self.cfg = cfg
        self.log = log or Log(cfg.log_level)
        self.metrics = Metrics()
        self.notify = Notifier()
        self.models: dict[str, Loaded] = {}
        self.sched = Scheduler(cfg.budget_ms, cfg.max_gap_frames, cfg.max_batch)
        self.sessions = SessionTable(self._resolve, cfg.max_streams, self._count)
        self.ctx: zmq.Context | None = None
        self.router = self.pull = self.sub = self.pub = None
        self.udp: socket.socket | None = None
        self.http: MetricsHTTP | None = None
        self._prom = ""
        self.flag_reload = False
        self.flag_stop = False
        self._reload_thread: threading.Thread | None = None
        self._reload_result: tuple[config_mod.Config | None, dict[str, Loaded], dict[str, str]] | None = None
        self._reload_waiters: list[Origin] = []
        self.last_reload: dict[str, Any] = {}
        self.started = time.time()

    # ---- models -----------------------------------------------------------------------------
    def _resolve(self, requested: str | None, sid: str):
        name = requested or self.cfg.stream_models.get(sid) or self.cfg.default_model
        if name not in self.models:
            raise KeyError(f"model {name!r} is not loaded (loaded: {', '.join(sorted(self.models))})")
        return name, self.models[name].model

    def _count(self, name: str, sid: str | None) -> None:
        self.metrics.inc(name)

    # ---- start ------------------------------------------------------------------------------
    def start(self) -> None:
        table, errors = load_all(self.cfg)
        if errors:
            raise config_mod.ConfigError("; ".join(f"model {n}: {e}" for n, e in errors.items()))
        self._install(table)
        self.ctx = zmq.Context()
        c = self.cfg
        hwm = c.zmq_hwm

        def sock(kind: int) -> zmq.Socket:
            s = self.ctx.socket(kind)  # type: ignore[union-attr]
            s.setsockopt(zmq.LINGER, 0)
            s.setsockopt(zmq.SNDHWM, hwm)
            s.setsockopt(zmq.RCVHWM, hwm)
            # beyond this ZeroMQ disconnects the peer without reading the message into memory;
            # between max_message_bytes and this the daemon reads it and answers `too_large`
            s.setsockopt(zmq.MAXMSGSIZE, max(ZMQ_MAXMSG_FLOOR, 4 * c.max_message_bytes))
            return s

        self.poller = zmq.Poller()
        if c.zmq_router:
            self.router = sock(zmq.ROUTER)
            self.router.bind(c.zmq_router)
            self.poller.register(self.router, zmq.POLLIN)
        if c.zmq_pull:
            self.pull = sock(zmq.PULL)
            self.pull.bind(c.zmq_pull)
            self.poller.register(self.pull, zmq.POLLIN)
        if c.zmq_sub:
            self.sub = sock(zmq.SUB)
            self.sub.setsockopt(zmq.SUBSCRIBE, b"")
            for ep in c.zmq_sub:
                self.sub.connect(ep)
            self.poller.register(self.sub, zmq.POLLIN)
        if c.zmq_pub:
            self.pub = sock(zmq.PUB)
            self.pub.bind(c.zmq_pub)
        if c.osc_listen:
            fam = socket.AF_INET6 if ":" in c.osc_listen[0] else socket.AF_INET
            self.udp = socket.socket(fam, socket.SOCK_DGRAM)
            self.udp.bind(c.osc_listen)
            self.udp.setblocking(False)
            self.poller.register(self.udp.fileno(), zmq.POLLIN)
        if c.metrics_http:
            self.http = MetricsHTTP(c.metrics_http[0], c.metrics_http[1], lambda: self._prom)
        self._prom = self.metrics.prometheus(self.status())
        self.log("info", "ready", pid=os.getpid(), config=c.path, endpoints=self.endpoints(),
                 models={n: m.info() for n, m in self.models.items()})
        self.notify.ready(self._status_line())

    def _install(self, table: dict[str, Loaded]) -> None:
        for name, ld in table.items():
            old = self.models.get(name)
            if old is not None and old.model is ld.model:
                continue
            self.sched.costs.update(ld.costs)
            if old is not None:
                n = self.sessions.rebind(name, ld.model)
                self.log("info", "model_swapped", model=name, file=ld.spec.file, streams=n)
        self.models = table

    def endpoints(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for name, s in (("router", self.router), ("pull", self.pull), ("pub", self.pub)):
            if s is not None:
                out[name] = s.getsockopt(zmq.LAST_ENDPOINT).decode()
        if self.sub is not None:
            out["sub"] = self.cfg.zmq_sub
        if self.udp is not None:
            out["osc"] = "%s:%d" % self.udp.getsockname()[:2]
        if self.http is not None:
            out["metrics_http"] = f"{self.cfg.metrics_http[0]}:{self.http.port}"  # type: ignore[index]
        return out

    # ---- signals ----------------------------------------------------------------------------
    def install_signals(self) -> None:
        signal.signal(signal.SIGHUP, lambda *_: setattr(self, "flag_reload", True))
        signal.signal(signal.SIGTERM, lambda *_: setattr(self, "flag_stop", True))
        signal.signal(signal.SIGINT, lambda *_: setattr(self, "flag_stop", True))

    # ---- main loop --------------------------------------------------------------------------
    def run(self) -> None:
        next_house = 0.0
        try:
            while True:
                pending = any(s.pending is not None for s in self.sessions.sessions.values())
                timeout = 0 if pending else IDLE_POLL_MS
                wd = self.notify.watchdog_due(time.monotonic())
                if wd is not None:
                    timeout = min(timeout, max(0, int(wd * 1000)))
                try:
                    ready = dict(self.poller.poll(timeout))
                except zmq.ZMQError as e:
                    if e.errno != errno.EINTR:
                        raise
                    ready = {}
                if ready:
                    self._ingest(ready)
                self._serve()
                if self.flag_stop:
                    break
                now = time.monotonic()
                if self.flag_reload:
                    self.flag_reload = False
                    self._start_reload(None)
                if self._reload_result is not None:
                    self._finish_reload()
                if now >= next_house:
                    next_house = now + HOUSEKEEPING_S
                    self._housekeeping(now)
            self._drain()
        finally:
            self.close()

    def _ingest(self, ready: dict) -> None:
        for sock_, name in ((self.router, "router"), (self.pull, "pull"), (self.sub, "sub")):
            if sock_ is None or sock_ not in ready:
                continue
            for _ in range(DRAIN_MAX):
                try:
                    parts = sock_.recv_multipart(zmq.NOBLOCK)
                except zmq.Again:
                    break
                arrived = time.perf_counter()
                if name == "router":
                    if len(parts) < 2:
                        self._reject(None, "bad_envelope", f"ROUTER message of {len(parts)} frame(s)", None, None)
                        continue
                    origin: Origin = ("router", parts[:-1])
                else:
                    origin = ("pull", None)
                self._handle(parts[-1], origin, arrived)
        if self.udp is not None and self.udp.fileno() in ready:
            for _ in range(DRAIN_MAX):
                try:
                    data, addr = self.udp.recvfrom(UDP_MAX)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError as e:  # e.g. ICMP port unreachable surfacing as ECONNREFUSED
                    self.metrics.inc("osc_recv_errors")
                    self.log("debug", "osc_recv_error", error=str(e))
                    continue
                self._handle(data, ("osc", addr), time.perf_counter())

    def _handle(self, data: bytes, origin: Origin, arrived: float) -> None:
        self.metrics.inc("messages_in")
        try:
            msg = osc.decode(data, self.cfg.max_message_bytes) if origin[0] == "osc" else wire.decode(data, self.cfg.max_message_bytes)
        except wire.WireError as e:
            self._reject(origin, e.reason, e.detail, e.stream, e.seq)
            return
        try:
            if isinstance(msg, wire.Frame):
                self.metrics.inc("frames_in")
                for o, m in self.sessions.frame(msg, origin, arrived):
                    self._send(o, m)
            elif isinstance(msg, wire.Hello):
                ack = self.sessions.hello(msg)
                self.log("info", "stream_hello", stream=msg.stream, model=ack.model, channels=len(ack.channels),
                         passthrough=len(ack.passthrough), missing=len(ack.missing))
                self._send(origin, ack)
            elif isinstance(msg, wire.Control):
                self._control(msg, origin)
            else:
                self._reject(origin, "unknown_type", f"{type(msg).__name__} is an answer, not a request", None, None)
        except SessionError as e:
            sid = getattr(msg, "stream", None)
            self._reject(origin, e.reason, e.detail, sid, getattr(msg, "seq", None))

    def _reject(self, origin: Origin | None, reason: str, detail: str, sid: str | None, seq: int | None) -> None:
        self.metrics.reject(reason)
        s = self.sessions.sessions.get(sid) if sid else None
        if s is not None:
            s.counts["rejected"] += 1
        self.log("warning", "rejected", reason=reason, detail=detail[:300], stream=sid, seq=seq,
                 transport=origin[0] if origin else None)
        if origin is not None:
            self._send(origin, wire.ErrorMsg(reason, detail, sid, seq))

    def _serve(self) -> None:
        groups: dict[int, tuple[Any, list]] = {}
        for s in self.sessions.sessions.values():
            if s.pending is not None:
                groups.setdefault(id(s.model), (s.model, []))[1].append(s)
        if not groups:
            return
        t0 = time.perf_counter()
        results = self.sched.run(groups, t0)
        self.metrics.step_time(time.perf_counter() - t0)
        t1 = time.perf_counter()
        for s, fill, status in results:
            p = s.pending
            now = time.perf_counter()
            msg = fill_message(s, fill, status, now)
            s.last_seq = p.frame.seq
            s.pending = None
            s.counts["frames_out"] += 1
            if status == "degraded":
                s.counts["degraded"] += 1
                self.metrics.inc("degraded")
            self.metrics.inc("frames_out")
            self.metrics.latency(now - p.arrived)
            self._send(p.origin, msg, publish=True)
        if results:
            per = (time.perf_counter() - t1) / len(results)
            self.sched.reply_cost = 0.9 * self.sched.reply_cost + 0.1 * per

    # ---- output -----------------------------------------------------------------------------
    def _send(self, origin: Origin, msg: wire.Message, publish: bool = False) -> None:
        kind = origin[0]
        try:
            if kind == "osc":
                dest = self.cfg.osc_send or origin[1]
                assert self.udp is not None
                self.udp.sendto(osc.encode(msg), dest)
            else:
                body = wire.encode(msg)
                if kind == "router" and self.router is not None:
                    self.router.send_multipart([*origin[1], body], zmq.NOBLOCK)
                elif kind == "pull" and self.pub is not None and not publish:
                    topic = getattr(msg, "stream", None) or ""
                    self.pub.send_multipart([topic.encode(), body], zmq.NOBLOCK)
                if publish and self.pub is not None:
                    self.pub.send_multipart([msg.stream.encode(), body], zmq.NOBLOCK)  # type: ignore[union-attr]
                return
            if publish and self.pub is not None:
                self.pub.send_multipart([msg.stream.encode(), wire.encode(msg)], zmq.NOBLOCK)  # type: ignore[union-attr]
        except zmq.Again:
            self.metrics.inc("send_dropped")  # peer over its high-water mark: drop, never block
        except (OSError, zmq.ZMQError) as e:
            self.metrics.inc("send_errors")
            self.log("debug", "send_error", transport=kind, error=str(e))

    # ---- control ----------------------------------------------------------------------------
    def _control(self, msg: wire.Control, origin: Origin) -> None:
        if msg.cmd == "status":
            self._send(origin, wire.ControlReply("status", True, self.status()))
        elif msg.cmd == "list-models":
            self._send(origin, wire.ControlReply("list-models", True, {"models": {n: m.info() for n, m in self.models.items()},
                                                                         "default": self.cfg.default_model}))
        elif msg.cmd == "reset":
            assert msg.stream is not None
            ok = self.sessions.reset(msg.stream)
            self.log("info", "stream_reset", stream=msg.stream, existed=ok)
            self._send(origin, wire.ControlReply("reset", ok, {"stream": msg.stream},
                                                 None if ok else f"no open stream {msg.stream!r}"))
        elif msg.cmd == "reload":
            self._start_reload(origin)

    def status(self) -> dict[str, Any]:
        return {
            "pid": os.getpid(), "uptime_s": round(time.time() - self.started, 3), "config": self.cfg.path,
            "budget_ms": self.cfg.budget_ms, "default_model": self.cfg.default_model,
            "models": {n: m.info() for n, m in self.models.items()},
            "latency": self.metrics.latency_summary(), "step": self.metrics.step_summary(),
            "counters": dict(self.metrics.counters), "rejected": dict(self.metrics.rejected),
            "streams": {sid: s.info() for sid, s in self.sessions.sessions.items()},
            "expired": self.sessions.expired, "step_errors": self.sched.step_errors,
            "last_step_error": self.sched.last_error, "reload": self.last_reload,
        }

    def _status_line(self) -> str:
        lat = self.metrics.latency_summary()
        p99 = lat.get("p99_ms")
        return (f"{len(self.sessions.sessions)} streams, {self.metrics.counters.get('frames_out', 0)} frames out, "
                f"p99 {p99 if p99 is not None else '-'} ms, models: {', '.join(self.models)}")

    # ---- reload -----------------------------------------------------------------------------
    def _start_reload(self, origin: Origin | None) -> None:
        if origin is not None:
            self._reload_waiters.append(origin)
        if self._reload_thread is not None and self._reload_thread.is_alive():
            return  # one at a time; the waiter gets this one's answer
        self.notify.reloading()
        self.log("info", "reload_start", config=self.cfg.path)
        old = dict(self.models)
        path = self.cfg.path

        def work() -> None:
            try:
                new_cfg = config_mod.load(path) if path else self.cfg
            except config_mod.ConfigError as e:
                self._reload_result = (None, old, {"config": str(e)})
                return
            table, errors = load_all(new_cfg, old)
            self._reload_result = (new_cfg, table, errors)

        self._reload_thread = threading.Thread(target=work, name="reload", daemon=True)
        self._reload_thread.start()

    def _finish_reload(self) -> None:
        new_cfg, table, errors = self._reload_result  # type: ignore[misc]
        self._reload_result = None
        if new_cfg is not None:
            moved = [k for k in ("zmq_router", "zmq_pull", "zmq_sub", "zmq_pub", "osc_listen", "metrics_http")
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
            self.sched.max_gap, self.sched.max_batch = new_cfg.max_gap_frames, new_cfg.max_batch
            self.sessions.max_streams = new_cfg.max_streams
            self.log = Log(new_cfg.log_level, self.log.stream)
        self._install(table)
        ok = not errors
        self.last_reload = {"at": time.time(), "ok": ok, "errors": errors,
                            "models": {n: m.loaded_at for n, m in self.models.items()}}
        self.metrics.inc("reloads" if ok else "reload_failures")
        for name, err in errors.items():
            self.log("error", "reload_refused", model=name, error=err, detail="the old model keeps serving")
        self.log("info", "reload_done", ok=ok, models=list(self.models))
        self.notify.ready(self._status_line())
        for o in self._reload_waiters:
            self._send(o, wire.ControlReply("reload", ok, {"models": {n: m.info() for n, m in self.models.items()},
                                                           "errors": errors},
                                            None if ok else "; ".join(f"{k}: {v}" for k, v in errors.items())))
        self._reload_waiters = []

    # ---- housekeeping / shutdown --------------------------------------------------------------
    def _housekeeping(self, now: float) -> None:
        gone = self.sessions.expire(now, self.cfg.idle_timeout_s)
        for sid in gone:
            self.log("info", "stream_expired", stream=sid)
            self.metrics.inc("expired")
        if self.http is not None:
            self._prom = self.metrics.prometheus(self.status())
        self.notify.status(self._status_line())

    def _drain(self) -> None:
        """SIGTERM: answer what has already arrived, then stop."""
        self.notify.stopping()
        self.log("info", "draining")
        for _ in range(3):
            try:
                ready = dict(self.poller.poll(0))
            except zmq.ZMQError:
                ready = {}
            if not ready:
                break
            self._ingest(ready)
            self._serve()
        self._serve()
        c = self.metrics.counters
        self.log("info", "stopped", frames_in=c.get("frames_in", 0), frames_out=c.get("frames_out", 0),
                 dropped=sum(v for k, v in c.items() if k.startswith("dropped_")))

    def close(self) -> None:
        for s in (self.router, self.pull, self.sub, self.pub):
            if s is not None:
                s.setsockopt(zmq.LINGER, DRAIN_LINGER_MS if self.flag_stop else 0)
                s.close()
        self.router = self.pull = self.sub = self.pub = None
        if self.udp is not None:
            self.udp.close()
            self.udp = None
        if self.http is not None:
            self.http.close()
            self.http = None
        if self.ctx is not None:
            self.ctx.term()
            self.ctx = None
        self.notify.close()


def serve(path: str) -> int:
    cfg = config_mod.load(path)
    log = Log(cfg.log_level)
    d = Daemon(cfg, log)
    d.install_signals()
    try:
        d.start()
    except Exception:
        d.close()
        raise
    d.run()
    return 0


def control(endpoint: str, cmd: str, stream: str | None = None, timeout_s: float = 5.0) -> wire.ControlReply:
    """One control request over a DEALER socket (what `lacuna status` uses)."""
    ctx = zmq.Context()
    s = ctx.socket(zmq.DEALER)
    s.setsockopt(zmq.LINGER, 0)
    try:
        s.connect(endpoint)
        s.send(wire.encode(wire.Control(cmd, stream)))
        if not s.poll(int(timeout_s * 1000)):
            raise TimeoutError(f"no answer from {endpoint} within {timeout_s:g} s (is `lacuna serve` running?)")
        m = wire.decode(s.recv(), 64 << 20)
        if isinstance(m, wire.ErrorMsg):
            raise ValueError(f"{endpoint} refused {cmd}: {m.reason}: {m.detail}")
        if not isinstance(m, wire.ControlReply):
            raise ValueError(f"{endpoint} answered {cmd} with a {type(m).__name__}")
        return m
    finally:
        s.close()
        ctx.term()

