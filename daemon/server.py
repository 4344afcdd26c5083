"""`lacuna serve`: the main loop.

One thread serves everything: ``poll(timeout)`` over the ZeroMQ sockets and the OSC UDP socket,
drain what arrived (bounded), decode, hand frames to their sessions (conflating per stream),
one batched scheduler step per model, answer, then answer the frames of the burst that a newer
frame of their stream superseded (set aside undecoded, see ``_batch``), then housekeeping
against deadlines (watchdog, idle expiry, metrics snapshot, signal flags).  Signal handlers
only set flags.  A reload loads and checks the new models on a helper thread and swaps them
between two ticks, so no frame is dropped or held up by the load; a file that fails keeps the
old model and the log says why.
"""
from __future__ import annotations

import gc
import json
import os
import signal
import sys
import time
from typing import Any

import zmq

from daemon import config as config_mod
from daemon import budget as budgets, osc, wire
from daemon.metrics import Metrics
from daemon.metrics_http import MetricsHTTP
from daemon.models import Loaded, load_all
from daemon.notify import Notifier
from daemon.pmqos import CpuLatency
from daemon.realtime import Realtime, ordinary
from daemon.reload import Reloader
from daemon.prewarm import Prewarm
from daemon.scheduler import Scheduler, fill_messages
from daemon.stalls import Stalls
from daemon.session import Origin, SessionError, SessionTable, principal
from daemon.transport import Transports

OSC_ERRORS_PER_S = 20  # error answers a second to one OSC source host; the rest are counted, not sent
OSC_ERROR_FLOOR = 64  # bytes an OSC error answer may take even when what it answers was smaller (a reason code)
STATUS_STREAMS = 256  # streams `status` details by default, most recently active first (`limit` asks for more)
PROM_STREAMS = 64  # streams with per-stream series in the metrics snapshot
SLICE = 16  # messages of a barrier burst between two looks at the clock (see _batch)
BATCH_MIN = 3  # messages in a turn from which frames superseded within it are answered after the step
IDLE_POLL_MS = 100  # poll timeout when nothing is pending (signal flags are read at least this often)
HOUSEKEEPING_S = 0.5
RELOAD_SWITCH_S = 0.0005  # sys.setswitchinterval while a reload thread runs (see _start_reload)
REJECT_LOG_PER_S = 20  # rejection log lines per second; the rest are counted, summarised
DRAIN_LINGER_MS = 1000  # on SIGTERM, let answers already queued reach their peers
LEVELS = {"debug": 10, "info": 20, "warning": 30, "error": 40}


class Log:
    """JSON lines on stderr: {"ts", "level", "event", ...fields}."""

    def __init__(self, level: str = "info", stream: Any = None):
        self.level = LEVELS[level]
        self.stream = stream or sys.stderr

    def __call__(self, level: str, event: str, always: bool = False, **fields: Any) -> None:
        # lifecycle events (ready, reload_done, stopped) are logged whatever the level: tools
        # and tests wait for them
        if LEVELS[level] < self.level and not always:
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
        self.qos = CpuLatency()
        self.rt = Realtime()
        self.models: dict[str, Loaded] = {}
        self.sched = Scheduler(cfg.budget_ms, cfg.max_gap_frames, cfg.max_batch)
        self.sessions = SessionTable(self._resolve, cfg.max_streams, self._count)
        self.sessions.idle_s = cfg.idle_timeout_s  # (an owner silent this long gives its stream up)
        self.net: Transports | None = None
        self.http: MetricsHTTP | None = None
        self._prom = ""
        self.flag_reload = False
        self.flag_stop = False
        self.reloader: Reloader | None = None  # started with the daemon (no thread is started at reload time)
        self._reload_args: tuple[str | None, dict[str, Loaded]] = (None, {})
        self._switch = sys.getswitchinterval()  # restored when a reload finishes
        self.last_reload: dict[str, Any] = {}
        self.started = time.time()
        self._rej_window, self._rej_logged, self._rej_suppressed = 0.0, 0, 0
        self._last_rx = 0.0  # perf_counter of the last poll that found a message (busy_poll_ms)
        # frames a newer one superseded within a burst, answered after the turn's fills (_batch):
        # (session, its last answered seq before the burst, the served frame's Pending,
        #  [(unpacked map, origin, arrived) or None where the served frame came, ...])
        self._superseded: list[tuple[Any, int | None, Any, list[tuple[Any, Origin, float] | None]]] = []
        self._conflated: list[tuple[Origin, wire.Message]] = []  # this turn's `conflated` and `overdue` drops, sent after its fills
        self._drop_overdue = self.cfg.overdue == "drop"
        self.prewarm = Prewarm(cfg.prewarm_ms)
        self.stalls = Stalls()  # how late the loop woke (a stopped or starved process), daemon/stalls.py
        self.budget = budgets.Budget()  # hello/control requests per peer (daemon/budget.py)
        self.osc_err_budget = budgets.Budget(OSC_ERRORS_PER_S, OSC_ERRORS_PER_S)  # error answers per OSC source host
        self._osc_in = 0  # bytes of the OSC datagram being handled (its answers may not be larger)
        self._osc_errs: list[tuple[str, str]] | None = None  # errors of the OSC bundle being handled

    @property
    def _busy_s(self) -> float:
        return self.cfg.busy_poll_ms / 1000.0   # read each time: a reload may change it

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
        self.reloader = Reloader(self._reload_work, self._reload_started)
        # the log object changes on reload (level): look it up at each call
        self.net = Transports(self.cfg, self._handle, self._reject, self.metrics, lambda *a, **k: self.log(*a, **k),
                              self._batch)
        self.net.open()
        if self.cfg.metrics_http:
            self.http = MetricsHTTP(self.cfg.metrics_http[0], self.cfg.metrics_http[1], lambda: self._prom,
                                    allow=self.cfg.metrics_networks)
        self._request_cpu_latency()
        self._request_realtime()  # (after every thread the daemon starts for good, so only these get it)
        self._prom = self.metrics.prometheus(self.status())
        self.log("info", "ready", always=True, pid=os.getpid(), config=self.cfg.path, endpoints=self.endpoints(),
                 models={n: m.info() for n, m in self.models.items()})
        self.notify.ready(self._status_line())

    def _install(self, table: dict[str, Loaded]) -> None:
        for name, ld in table.items():
            old = self.models.get(name)
            if old is not None and old.model is ld.model:
                continue
            if old is not None:
                self.sched.forget(old.model)  # costs are keyed by id(): never let a new object inherit them
            self.sched.costs.update(ld.costs)
            if old is not None:
                n = self.sessions.rebind(name, ld.model)
                self.log("info", "model_swapped", model=name, file=ld.spec.file, streams=n)
        self.models = table
        self.prewarm.forget_models()

    def _request_cpu_latency(self) -> None:
        us = self.cfg.cpu_latency_us
        if us == self.qos.requested_us and (self.qos.held or us is None):
            return
        if self.qos.request(us):
            self.log("info", "cpu_latency", requested_us=us, effective_us=self.qos.effective_us(),
                     detail="CPUs kept out of idle states slower to leave than this while the daemon runs")
        elif us is not None:
            self.metrics.inc("cpu_latency_refused")
            self.log("warning", "cpu_latency_refused", requested_us=us, error=self.qos.error,
                     detail="serving without it; see systemd/lacuna.service for granting the device")

    def _request_realtime(self) -> None:
        prio = self.cfg.realtime_priority
        if prio == self.rt.requested:
            return  # (held, or refused: tried again only when the config asks for another priority)
        n_io = self.net.ctx.get(zmq.IO_THREADS) if self.net is not None and self.net.ctx is not None else 0
        if self.rt.request(prio, n_io):
            self.log("info", "realtime", priority=prio, threads=self.rt.info()["threads"],
                     detail="the serving thread and ZeroMQ's I/O threads run SCHED_RR ahead of ordinary work")
        elif prio is not None:
            self.metrics.inc("realtime_refused")
            self.log("warning", "realtime_refused", priority=prio, error=self.rt.error,
                     detail="serving at the ordinary priority; see systemd/lacuna.service for LimitRTPRIO")

    def endpoints(self) -> dict[str, Any]:
        out = self.net.endpoints() if self.net is not None else {}
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
                pending = bool(self.sessions.waiting)  # (cost: the streams with a frame, not the open ones)
                timeout = 0 if pending else IDLE_POLL_MS
                wd = self.notify.watchdog_due(time.monotonic())
                if wd is not None:
                    timeout = min(timeout, max(0, int(wd * 1000)))
                pw = self.prewarm
                if timeout and pw.due is not None:
                    # the next frame is due soon: warm the path it takes (daemon/prewarm.py); the
                    # poll's timeout is whole milliseconds, so this runs lead to lead + 1 ms ahead
                    left = pw.due - time.perf_counter()
                    if left < 0.001:
                        pw.rehearse(self.sessions.sessions, self.sched, self.net._encode)  # type: ignore[union-attr]
                    else:
                        timeout = min(timeout, int(left * 1000))
                self.stalls.sleeping()
                due = time.perf_counter() + timeout / 1000.0
                if timeout and self._busy_s:
                    due += max(0.0, self._last_rx + self._busy_s - time.perf_counter())
                    ready = self._spin(timeout)
                else:
                    ready = self.net.poll(timeout)  # type: ignore[union-attr]
                self.stalls.woke(due)
                net = self.net
                net.hold()  # type: ignore[union-attr]  # this turn's answers go out together, after its work
                try:
                    if ready:
                        self._last_rx = time.perf_counter()
                        net.receive(ready)  # type: ignore[union-attr]
                    self._serve()
                    if self._superseded or self._conflated:
                        self._send_held()  # what came since the fills (they are out already)
                        self._answer_superseded()
                except Exception as e:  # never let a bug end the service: log, count, go on
                    self.metrics.inc("internal_errors")
                    self.log("error", "internal_error", where="loop", error=f"{type(e).__name__}: {e}"[:300])
                    self._abandon_pending(f"{type(e).__name__} while serving")
                finally:
                    self._send_held(hold_on=False)
                if self.flag_stop:
                    break
                now = time.monotonic()
                try:  # (a failure here, a thread or a resource, must not end the daemon either)
                    if self.flag_reload:
                        self.flag_reload = False
                        self._start_reload(None)
                    done = self.reloader.poll()  # type: ignore[union-attr]
                    if done is not None:
                        try:
                            self._finish_reload(*done)
                        finally:
                            self.reloader.kick()  # type: ignore[union-attr]
                    if now >= next_house:
                        next_house = now + HOUSEKEEPING_S
                        self._housekeeping(now)
                except Exception as e:
                    self.metrics.inc("internal_errors")
                    self.log("error", "internal_error", where="housekeeping", error=f"{type(e).__name__}: {e}"[:300])
            self._drain()
        finally:
            self.close()

    def _spin(self, timeout_ms: int) -> dict:
        """Busy-poll (``busy_poll_ms``): for that long after the last message arrived, poll without
        sleeping, so the next frame is picked up as soon as it lands instead of after the kernel
        wakes the thread (0.3-1 ms on a virtual machine, most of a loopback round trip).  Costs a
        core while frames flow; once the stream pauses for longer, sleep in poll as usual."""
        end = self._last_rx + self._busy_s
        net = self.net
        while time.perf_counter() < end:
            ready = net.poll(0)  # type: ignore[union-attr]
            if ready or self.flag_stop or self.flag_reload:
                return ready
            os.sched_yield()  # let ZeroMQ's I/O thread, which moves the bytes, run on this core at once
        return net.poll(timeout_ms)  # type: ignore[union-attr]

    def _handle(self, data: bytes, origin: Origin, arrived: float, counted: bool = False) -> None:
        if not counted:
            self.metrics.inc("messages_in")
        if origin[0] != "osc":
            try:
                m = wire.unpack(data, self.cfg.max_message_bytes)
            except wire.WireError as e:
                self._reject(origin, e.reason, e.detail, e.stream, e.seq)
                return
            self._handle_map(m, origin, arrived)
        elif data.startswith(osc.BUNDLE_PREFIX):  # several messages of one instant
            self._osc_in, self._osc_errs = len(data), []
            try:
                self._take(self._osc_bundle, data, origin, arrived)
            finally:
                errs, self._osc_errs = self._osc_errs, None
                if errs:
                    self._osc_summary(origin, errs)
        else:
            self._osc_in = len(data)
            self._take(osc.decode, data, origin, arrived)

    def _handle_map(self, m: dict | wire.WireError | bytes, origin: Origin, arrived: float) -> None:
        """:meth:`_handle` for a message already unpacked by :meth:`_batch` (or its unpack error;
        bytes: an OSC datagram, not unpacked), counted there."""
        if type(m) is bytes:
            self._handle(m, origin, arrived, counted=True)
        elif isinstance(m, wire.WireError):
            self._reject(origin, m.reason, m.detail, m.stream, m.seq)
        elif m.get("type") == "hello" and (units := budgets.names_cost(m)) and \
                not self.budget.allow(principal(origin), units):
            # (before decoding: checking a hello's names is the cost the budget is for)
            self._rate_limited(origin, m)
        else:
            self._take(_decode_map, m, origin, arrived)

    def _rate_limited(self, origin: Origin, m: dict | None = None) -> None:
        sid = m.get("stream") if m is not None else None
        self._reject(origin, "rate_limited", f"over this peer's budget for hello/control requests "
                                             f"({budgets.RATE:g} cost units a second, bursts of {budgets.BURST:g}; "
                                             f"a hello costs 1 + channels/64, a control request {budgets.CONTROL_COST:g})",
                     sid if isinstance(sid, str) else None, None)

    def _osc_bundle(self, data: bytes, maxb: int) -> list[Any]:
        items = osc.decode_bundle(data, maxb)
        self.metrics.inc("osc_bundles_in")
        return items

    def _take(self, decode: Any, data: Any, origin: Origin, arrived: float) -> None:
        """``decode(data, max_message_bytes)`` (a message, or an OSC bundle's list of them) and
        dispatch; what cannot be decoded is answered with its error, and a malformed element of
        a bundle costs only itself."""
        try:
            got = decode(data, self.cfg.max_message_bytes)
        except wire.WireError as e:
            self._reject(origin, e.reason, e.detail, e.stream, e.seq)
            return
        except Exception as e:  # a decoder bug must cost one message, never the loop
            self._internal("decode", e, origin, None, None)
            return
        for m in got if type(got) is list else (got,):
            if isinstance(m, wire.WireError):
                self._reject(origin, m.reason, m.detail, m.stream, m.seq)
            else:
                self._dispatch(m, origin, arrived)

    def _internal(self, where: str, e: Exception, origin: Origin | None, sid: str | None, seq: int | None) -> None:
        self.metrics.inc("internal_errors")
        self.log("error", "internal_error", where=where, stream=sid, error=f"{type(e).__name__}: {e}"[:300])
        self._reject(origin, "internal", f"{type(e).__name__} while handling the message", sid, seq)

    def _batch(self, items: list[tuple[bytes, Origin, float]]) -> None:
        """A turn's ZeroMQ messages, in arrival order.  Under a backlog most of them are frames
        that a newer frame of the same stream in the same burst supersedes; only the newest is
        served.  Those superseded frames are set aside, each burst only unpacked, and handled
        after the turn's fills went out (:meth:`_answer_superseded`), so the frames served do
        not wait for them.  Everything else is handled now, in order.

        The answers are exactly those of handling every message in order: a set-aside frame is
        decoded and checked later through the same session code, against the stream's state
        as it was before the burst, and nothing is set aside when the burst has a message that
        changes sessions (hello, control, bundle), for a stream that is new or has a frame
        waiting, or when the frame meant to supersede them is not taken (malformed, say): then
        they are handled at once, in order."""
        if len(items) < BATCH_MIN:
            for data, origin, arrived in items:
                self._handle(data, origin, arrived)
            return
        self.metrics.inc("messages_in", len(items))
        maxb = self.cfg.max_message_bytes
        maps: list[dict | wire.WireError | bytes] = []
        keys: list[tuple[str, int] | None] = []
        barrier = False
        for data, origin, _ in items:
            k = None
            if origin[0] == "osc":  # OSC is decoded on its own path, in order
                m: dict | wire.WireError | bytes = data
                barrier = True
            else:
                try:
                    m = wire.unpack(data, maxb)
                except wire.WireError as e:
                    m = e
            if type(m) is dict:
                k = wire.frame_key(m)
                if k is None and m.get("type") != "frame":
                    barrier = True  # hello, control, bundle, ...: handled in order with everything else
            maps.append(m)
            keys.append(k)
        chains: dict[str, list[int]] = {}  # stream -> indices set aside, behind its newest frame
        if not barrier:
            sessions = self.sessions.sessions
            # only streams with an owner that is not about to lose them (a frame from anyone
            # else is then refused whatever came before it: a released stream's adoption and a
            # silent owner's takeover depend on the order, so those bursts go in order)
            fresh = time.monotonic() - self.sessions.idle_s / 2
            single: dict[str, Any] = {}  # unowned stream -> its one sender in the burst (False: several)
            for k, it in zip(keys, items):
                if k is not None and (s := sessions.get(k[0])) is not None and s.owner is None:
                    w = principal(it[1])
                    if single.setdefault(k[0], w) != w:
                        single[k[0]] = False
            newest: dict[str, int] = {}
            for i, k in enumerate(keys):
                if k is None:
                    continue
                sid, seq = k
                j = newest.get(sid)
                if j is None:
                    s = sessions.get(sid)
                    if s is not None and s.pending is None and s.last_active > fresh and \
                            (s.owner is not None or single.get(sid) is not False):
                        newest[sid] = i
                elif seq > keys[j][1]:  # type: ignore[index]
                    chains.setdefault(sid, []).append(j)
                    newest[sid] = i
                else:  # not newer than the newest so far: answered late/duplicate with the chain
                    chains.setdefault(sid, []).append(i)
            heads = {newest[sid]: sid for sid in chains}
            aside = {i for c in chains.values() for i in c}
        else:
            heads, aside = {}, set()
        # a burst of costly requests (hellos, controls: that is what makes it a barrier) must not
        # hold up the frames read with it: every SLICE messages, once a quarter of the budget is
        # spent, the frames taken so far are served (as if the rest had come in the next turn)
        slice_at, t_slice = (SLICE if barrier else len(maps) + 1), time.perf_counter()
        frames_seen = self.metrics.counters.get("frames_in", 0)
        for i, (m, (_, origin, arrived)) in enumerate(zip(maps, items)):
            if i in aside:
                continue
            if i and not i % slice_at and time.perf_counter() - t_slice > self.sched.budget_s / 4:
                if self.metrics.counters.get("frames_in", 0) != frames_seen:
                    self._serve()
                    frames_seen = self.metrics.counters.get("frames_in", 0)
                t_slice = time.perf_counter()
            self._handle_map(m, origin, arrived)
            sid = heads.get(i)
            if sid is None:
                continue
            order = sorted(chains[sid] + [i])  # the stream's frames of the burst, in arrival order
            s = self.sessions.sessions[sid]
            p = s.pending
            if p is not None and p.frame.seq == keys[i][1]:  # type: ignore[index]
                # with None where the served frame came
                self._superseded.append((s, s.last_seq, p, [None if d == i else (maps[d], items[d][1], items[d][2])
                                                            for d in order]))
            else:  # the newest frame was refused and changed nothing: the rest count as usual
                for d in order:
                    if d != i:
                        self._handle_map(maps[d], items[d][1], items[d][2])

    def _frame_answers(self, out: list) -> None:
        """A session's immediate answers to a frame: a ``conflated`` drop (of the frame it
        replaced) waits for the turn's fills (:meth:`_answer_superseded`), the rest go now."""
        for o, m in out:
            if type(m) is wire.Drop and m.reason == "conflated":
                self._conflated.append((o, m))
            else:
                self._send(o, m)

    def _answer_superseded(self) -> None:
        """After the turn's fills: the ``conflated`` drops of the turn, and the frames
        :meth:`_batch` set aside, each decoded and taken by its session as it would have been
        in arrival order, before the frame that was served (the stream's last answered seq put
        back, no frame waiting), so it gets the answer it would have had then (``drop``
        conflated, late or duplicate, or an ``error``)."""
        self._send_conflated()
        todo, self._superseded = self._superseded, []
        for s, last_seq, served, chain in todo:
            # (the burst held no hello or reset, so the session is the same object; a SIGHUP swap
            # runs between turns and keeps it)
            assert self.sessions.sessions.get(s.sid) is s and s.pending is None
            now_seq, s.last_seq = s.last_seq, last_seq
            try:
                for item in chain:
                    if item is None:  # where the served frame came: it supersedes the one waiting
                        self._frame_answers(self.sessions.conflate(s))
                        s.pending = served  # (frames after it are late or duplicates against it)
                    else:
                        self._handle_map(*item)
            finally:
                s.last_seq = now_seq
                s.pending = None
        self._send_conflated()

    def _send_conflated(self) -> None:
        todo, self._conflated = self._conflated, []
        for o, m in todo:
            self._send(o, m)

    def _dispatch(self, msg: Any, origin: Origin, arrived: float) -> None:
        try:
            if isinstance(msg, wire.Frame):
                self.metrics.inc("frames_in")
                self._frame_answers(self.sessions.frame(msg, origin, arrived, principal(origin)))  # type: ignore[union-attr]
            elif isinstance(msg, wire.Bundle):
                self._bundle(msg, origin, arrived)
            elif isinstance(msg, (wire.Hello, wire.Control)) and \
                    not self.budget.allow(principal(origin), budgets.HELLO_COST if isinstance(msg, wire.Hello)
                                          else budgets.CONTROL_COST):
                self._rate_limited(origin)
            elif isinstance(msg, wire.Hello):
                ack, orphans = self.sessions.hello(msg, principal(origin))  # type: ignore[union-attr]
                for o, m in orphans:
                    self._send(o, m)
                self.log("info", "stream_hello", stream=msg.stream, model=ack.model, channels=len(ack.channels),
                         passthrough=len(ack.passthrough), missing=len(ack.missing))
                self._send(origin, ack)
            elif isinstance(msg, wire.Control):
                self._control(msg, origin)
            else:
                self._reject(origin, "unknown_type", f"{type(msg).__name__} is an answer, not a request", None, None)
        except SessionError as e:
            self._reject(origin, e.reason, e.detail, getattr(msg, "stream", None), getattr(msg, "seq", None))
        except Exception as e:  # a bug must cost one message, never the loop
            self._internal("handle", e, origin, getattr(msg, "stream", None), getattr(msg, "seq", None))

    def _bundle(self, msg: wire.Bundle, origin: Origin, arrived: float) -> None:
        """Each frame of a bundle as if it had come alone, at the bundle's arrival; over ROUTER
        their answers are marked to go back together (a third origin element, see Transports)."""
        self.metrics.inc("bundles_in")
        who = principal(origin)  # type: ignore[union-attr]
        if origin[0] == "router":
            origin = (*origin, "bundle")
        for f in msg.items:
            if isinstance(f, wire.WireError):
                self._reject(origin, f.reason, f.detail, f.stream, f.seq)
                continue
            self.metrics.inc("frames_in")
            try:
                self._frame_answers(self.sessions.frame(f, origin, arrived, who))
            except SessionError as e:  # one frame's refusal is its own answer; the rest go on
                self._reject(origin, e.reason, e.detail, f.stream, f.seq)
            except Exception as e:
                self.metrics.inc("internal_errors")
                self.log("error", "internal_error", where="bundle", stream=f.stream, error=f"{type(e).__name__}: {e}"[:300])
                self._reject(origin, "internal", f"{type(e).__name__} while handling the frame", f.stream, f.seq)

    def _reject(self, origin: Origin | None, reason: str, detail: str, sid: str | None, seq: int | None) -> None:
        self.metrics.reject(reason)
        s = self.sessions.sessions.get(sid) if sid else None
        if s is not None and reason != "not_owner":  # (someone else's message: counted `foreign` on the stream)
            s.counts["rejected"] += 1
        # a flood of bad input must not turn into a flood of log lines: at most REJECT_LOG_PER_S
        # a second are written, the rest are summed into one line per housekeeping tick
        now = time.monotonic()
        if now - self._rej_window >= 1.0:
            self._rej_window, self._rej_logged = now, 0
        if self._rej_logged < REJECT_LOG_PER_S:
            self._rej_logged += 1
            self.log("warning", "rejected", reason=reason, detail=detail[:300], stream=sid, seq=seq,
                     transport=origin[0] if origin else None)
        else:
            self._rej_suppressed += 1
        if origin is None:
            return
        if origin[0] == "osc":
            if self._osc_errs is not None:  # an element of a bundle: one answer for them all, after it
                self._osc_errs.append((reason, detail))
            else:
                self._osc_error(origin, wire.ErrorMsg(reason, detail, sid, seq))
            return
        self._send(origin, wire.ErrorMsg(reason, detail, sid, seq))

    # ---- OSC error answers: bounded (no amplification, no reflection flood) ---------------
    def _osc_summary(self, origin: Origin, errs: list[tuple[str, str]]) -> None:
        by: dict[str, int] = {}
        for r, _ in errs:
            by[r] = by.get(r, 0) + 1
        counts = ", ".join(f"{r} x{n}" for r, n in sorted(by.items(), key=lambda kv: -kv[1]))
        self._osc_error(origin, wire.ErrorMsg(errs[0][0], f"{len(errs)} message(s) of the bundle refused ({counts}); "
                                                         f"first: {errs[0][1]}"))

    def _osc_error(self, origin: Origin, msg: wire.ErrorMsg) -> None:
        """An OSC error answer, at most OSC_ERRORS_PER_S a second per source host and no larger
        than the datagram it answers or OSC_ERROR_FLOOR bytes, whichever is more (the detail
        is cut to fit; an answer that cannot fit is not sent): spoofing a source cannot turn
        the daemon into an amplifier."""
        if not self.osc_err_budget.allow(origin[1][0]):
            self.metrics.inc("osc_errors_unanswered")
            return
        room = max(self._osc_in, OSC_ERROR_FLOOR)
        data = osc.encode(msg)
        if len(data) > room:
            base = len(osc.encode(wire.ErrorMsg(msg.reason, "")))
            keep = room - base - 4  # (the detail's terminator and padding)
            if keep < 0:
                self.metrics.inc("osc_errors_unanswered")
                return
            msg = wire.ErrorMsg(msg.reason, msg.detail.encode()[:keep].decode(errors="ignore"), msg.stream, msg.seq)
        self._send(origin, msg)

    def _serve(self) -> None:
        pend = self.sessions.take_waiting()
        if not pend:
            return
        t0 = time.perf_counter()
        if self._drop_overdue:
            late = self.sched.overdue([s.pending.arrived for s in pend], t0,  # type: ignore[union-attr]
                                      [s.late_streak for s in pend])
            if True in late:
                # (answered after the fills, as conflated frames are)
                for s, x in zip(pend, late):
                    if x:
                        self._conflated.extend(self.sessions.overdue(s))
                pend = [s for s, x in zip(pend, late) if not x]
                if not pend:
                    return
        groups: dict[tuple[int, int], tuple[Any, list]] = {}
        for s in pend:
            # by width too: a pass-through "any channels" model serves streams of different
            # widths, and one batch stacks frames of one width
            groups.setdefault((id(s.model), s.mapping.n_model), (s.model, []))[1].append(s)
        results = self.sched.run(groups, t0)
        if len(results) > 1:
            # answered oldest first: the frame that arrived first is the nearest its budget
            # (earliest deadline first), and each reply is a few dozen microseconds of the tick
            results.sort(key=_arrival)
        self.metrics.inc("ticks")  # frames_out / ticks = the mean batch the scheduler stepped
        self.metrics.step_time(time.perf_counter() - t0)
        t1 = time.perf_counter()
        msgs = fill_messages(results, t1)  # reads s.pending and s.last_seq (for gap)
        t1e = time.perf_counter()
        sent: list[tuple[Any, float]] = []
        n, budget, sent_at = len(results), self.sched.budget_s, self.sched.sent_at
        for k, ((s, fill, status), msg) in enumerate(zip(results, msgs)):
            p = s.pending
            if isinstance(msg, Exception):  # a fill the wire cannot carry: answer with an error, keep serving
                s.last_seq, s.pending = p.frame.seq, None
                e = msg
                self.log("error", "internal_error", where="fill_message", stream=s.sid, error=f"{type(e).__name__}: {e}"[:300])
                self._reject(p.origin, "internal", f"{type(e).__name__} while encoding the fill", s.sid, p.frame.seq)
                continue
            now = time.perf_counter()
            # (a bundle's answers leave together, in one `replies`, after the tick's other answers)
            if self._drop_overdue and sent_at(now, n - k, n if len(p.origin) == 3 else len(sent) + 1) - p.arrived > budget:
                # the step ran longer than planned (most often the OS gave the CPU to someone
                # else): by the time this fill would leave it would be over budget.  The filter
                # has taken the frame; the answer is the drop the plan would have made.
                self.metrics.inc("overdue_after_step")
                self._conflated.extend(self.sessions.overdue(s))
                continue
            s.last_seq = p.frame.seq
            s.pending = None
            s.late_streak = 0
            # receipt to this reply's encoding (it is sent with the tick's other replies, below)
            msg.proc_us = int((now - p.arrived) * 1e6)
            s.counts["frames_out"] += 1
            if status == "degraded":
                s.counts["degraded"] += 1
                self.metrics.inc("degraded")
                # held (hold-last-value) vs stepped with fewer Gibbs iterations
                self.metrics.inc("degraded_held" if fill.degraded else "degraded_iterations")
            self.metrics.inc("frames_out")
            sent.append((s, p.arrived))
            last = (s, p.frame, p.arrived)
            self._send(p.origin, msg, publish=True)
        te = time.perf_counter()
        self._send_held(len(sent))  # the fills leave now; the turn's drops after them
        if sent and self.prewarm.on:
            self.prewarm.served(*last, self.sched)
        if results:
            t2 = time.perf_counter()
            # what a reply costs (the plan and the overdue checks use it)
            self.sched.observe_replies(n, te - t1e, t2 - t1)
            # receipt to sent: the latency in `status` and the over-budget count (an upper bound
            # for each reply of the tick: all of them had left by t2)
            lat = self.metrics.latency
            over = 0
            for s, arrived in sent:
                lat(t2 - arrived)
                if t2 - arrived > budget:
                    s.counts["over_budget"] += 1
                    over += 1
            if over:
                self.metrics.inc("over_budget", over)

    def _send_held(self, answers: int | None = None, hold_on: bool = True) -> None:
        """Send the answers held so far (and hold again, or not), timing it for the scheduler:
        per answer (``answers``: how many of them are the caller's to count; a fill also goes
        to PUB, so it is more than one message), else per message sent."""
        net = self.net
        if net is None:
            return
        t0 = time.perf_counter()
        n = net.send_held() if hold_on else net.flush()
        if answers:
            n = answers
        if n:
            self.sched.observe_sends(n, time.perf_counter() - t0)

    def _abandon_pending(self, why: str) -> None:
        """After a failed tick: answer every waiting frame (and every frame set aside as
        superseded) with an error rather than retrying the same failure in a tight loop."""
        todo, self._superseded = self._superseded, []
        try:
            self._send_conflated()  # (those frames were answered already: drops owed, not errors)
        except Exception:
            self._conflated = []
        owed = [(p.origin, s.sid, p.frame.seq) for s in self.sessions.sessions.values() if (p := s.pending) is not None]
        owed += [(origin, s.sid, k[1] if isinstance(m, dict) and (k := wire.frame_key(m)) else None)
                 for s, _, _, chain in todo for m, origin, _ in filter(None, chain)]
        for s in self.sessions.sessions.values():
            s.pending = None
        for origin, sid, seq in owed:
            try:
                self._reject(origin, "internal", why, sid, seq)
            except Exception:  # the answer itself failing must not stop the loop either
                pass

    # ---- output -----------------------------------------------------------------------------
    def _send(self, origin: Origin, msg: wire.Message, publish: bool = False) -> None:
        if self.net is not None:
            self.net.send(origin, msg, publish)

    # ---- control ----------------------------------------------------------------------------
    def _control(self, msg: wire.Control, origin: Origin) -> None:
        if msg.cmd == "status":
            if msg.stream is not None and msg.stream not in self.sessions.sessions:
                self._send(origin, wire.ControlReply("status", False, {}, f"no open stream {msg.stream!r}"))
                return
            n = STATUS_STREAMS if msg.limit is None else msg.limit
            if n > STATUS_STREAMS and not self.budget.allow(principal(origin), (n - STATUS_STREAMS) / 64.0):
                self._rate_limited(origin)  # (a long listing costs its length)
                return
            self._send(origin, wire.ControlReply("status", True, self.status(n, msg.stream)))
        elif msg.cmd == "list-models":
            self._send(origin, wire.ControlReply("list-models", True, {"models": {n: m.info() for n, m in self.models.items()},
                                                                         "default": self.cfg.default_model}))
        elif msg.cmd == "reset":
            assert msg.stream is not None
            ok, orphans = self.sessions.reset(msg.stream, principal(origin), self._operator(origin))  # type: ignore[union-attr]
            for o, m in orphans:
                self._send(o, m)
            self.log("info", "stream_reset", stream=msg.stream, existed=ok)
            self._send(origin, wire.ControlReply("reset", ok, {"stream": msg.stream},
                                                 None if ok else f"no open stream {msg.stream!r}"))
        elif msg.cmd == "release":
            assert msg.stream is not None
            ok = self.sessions.release(msg.stream, principal(origin))
            self._send(origin, wire.ControlReply("release", ok, {"stream": msg.stream},
                                                 None if ok else f"no open stream {msg.stream!r}"))
        elif msg.cmd == "reload":
            if not self._operator(origin):  # type: ignore[union-attr]
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

    # ---- housekeeping / shutdown --------------------------------------------------------------
    def _housekeeping(self, now: float) -> None:
        if self._rej_suppressed:
            self.log("warning", "rejected_not_logged", count=self._rej_suppressed,
                     by_reason=dict(self.metrics.rejected), detail="more rejections than the log takes; all are counted")
            self._rej_suppressed = 0
        gone = self.sessions.expire(now, self.cfg.idle_timeout_s)
        for sid in gone:
            self.log("info", "stream_expired", stream=sid)
            self.metrics.inc("expired")
        if self.http is not None:  # (per-stream series for the most recently active only)
            self._prom = self.metrics.prometheus(self.status(PROM_STREAMS))
        self.notify.status(self._status_line())

    def _drain(self) -> None:
        """SIGTERM: answer what has already arrived, then stop."""
        self.notify.stopping()
        self.log("info", "draining")
        assert self.net is not None
        for _ in range(3):
            ready = self.net.poll(0)
            if not ready:
                break
            self.net.receive(ready)
            self._serve()
            self._answer_superseded()
        self._serve()
        self._answer_superseded()
        c = self.metrics.counters
        self.log("info", "stopped", always=True, frames_in=c.get("frames_in", 0), frames_out=c.get("frames_out", 0),
                 dropped=sum(v for k, v in c.items() if k.startswith("dropped_")),
                 send_dropped=c.get("send_dropped", 0), send_errors=c.get("send_errors", 0))

    def close(self) -> None:
        if self.reloader is not None:
            self.reloader.stop()
        self.rt.release()  # (before the ZeroMQ threads end: their ids must not be reused by then)
        if self.net is not None:
            self.net.close(DRAIN_LINGER_MS if self.flag_stop else 0)
            self.net = None
        if self.http is not None:
            self.http.close()
            self.http = None
        self.qos.release()
        self.notify.close()


def _decode_map(m: dict, max_bytes: int) -> wire.Message:
    return wire.decode_map(m)  # (already unpacked, within max_bytes)


def _arrival(r: tuple) -> tuple[float, int]:
    # (frames read together, a bundle's: the streams that were dropped `overdue` most go first)
    return r[0].pending.arrived, -r[0].late_streak


def serve(path: str) -> int:
    from lacuna.blas import limit_process_blas

    cfg = config_mod.load(path)
    blas = limit_process_blas()  # noqa: F841  (kept alive for the daemon's lifetime)
    log = Log(cfg.log_level)
    d = Daemon(cfg, log)
    d.install_signals()
    try:
        d.start()
    except Exception:
        d.close()
        raise
    # everything loaded so far lives as long as the daemon: keep it out of the collector's
    # generations so the cyclic GC has less to walk in the middle of a frame
    gc.collect()
    gc.freeze()
    d.run()
    return 0
