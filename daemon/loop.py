"""`lacuna serve`: the daemon's lifecycle and its loop.

One thread serves everything: ``poll(timeout)`` over the ZeroMQ sockets and the OSC UDP socket
(daemon/wait.py: how long, and the rehearsal before a frame is due), then one :meth:`Daemon.turn`:
what arrived (bounded) is decoded and handed to its sessions (daemon/dispatch.py, conflating per
stream), one batched scheduler step per model answers the frames waiting (daemon/tick.py), then
the frames of the burst that a newer frame of their stream superseded are answered; then
housekeeping against deadlines (watchdog, idle expiry, metrics snapshot, signal flags, the cyclic
GC's full collection: `settle`).  Signal handlers only set flags.  A reload (daemon/reload.py)
loads and checks the new models on a helper thread and swaps them between two turns, so no frame
is dropped or held up by the load; a file that fails keeps the old model and the log says why.  Control requests: daemon/control.py.  The
data flow, file by file: transport.py -> dispatch.py (decode -> session.py) -> tick.py
(scheduler.py -> wire.py's encode) -> outbox.py; a studio's regular bundle takes the same steps as
arrays: blockpath.py (decode -> sessions) -> tickblock.py.
"""
from __future__ import annotations

import gc
import os
import signal
import sys
import time
from collections.abc import Callable
from typing import Any

import zmq

from daemon import budget as budgets
from daemon import config as config_mod
from daemon import wire
from daemon.control import Control
from daemon.dispatch import BATCH_MIN, OSC_ERRORS_PER_S, Dispatch
from daemon.layout import Layouts
from daemon.log import Log
from daemon.metrics import Metrics
from daemon.metrics_http import MetricsHTTP
from daemon.models import Loaded, load_all
from daemon.notify import Notifier
from daemon.pmqos import CpuLatency
from daemon.prewarm import Prewarm
from daemon.realtime import Realtime
from daemon.reload import Reloading
from daemon.reloader import Reloader
from daemon.scheduler import Scheduler
from daemon.session import Origin
from daemon.sessions import SessionTable
from daemon.stalls import Stalls
from daemon.tick import Tick
from daemon.transport import Transports
from daemon.wait import Waiting
from view import in_daemon

PROM_STREAMS = 64  # streams with per-stream series in the metrics snapshot
HOUSEKEEPING_S = 0.5
GEN2_EVERY = 10  # gen-1 collections between two full ones run by housekeeping (CPython's default)
GEN2_HELD = 1 << 30  # the gen-2 threshold while serving: no automatic full collection (settle)
DRAIN_LINGER_MS = 1000  # on SIGTERM, let answers already queued reach their peers


class Daemon(Dispatch, Tick, Control, Reloading, Waiting):
    def __init__(self, cfg: config_mod.Config, log: Log | None = None,
                 clock: Callable[[], float] = time.perf_counter):
        # the clock of receipt times, deadlines, idle expiry and slow steps (tests pass a fake one)
        self.clock = clock
        self.cfg = cfg
        self.log = log or Log(cfg.log_level)
        self.metrics = Metrics()
        self.notify = Notifier()
        self.qos = CpuLatency()
        self.rt = Realtime()
        self.models: dict[str, Loaded] = {}
        self.sched = Scheduler(cfg.budget_ms, cfg.max_gap_frames, cfg.max_batch, clock)
        self.sessions = SessionTable(self._resolve, cfg.max_streams, self._count, clock)
        self.sessions.idle_s = cfg.idle_timeout_s
        self._next_house = 0.0  # clock time of the next housekeeping  # (an owner silent this long gives its stream up)
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
        #  [a run of kept heads (daemon/aside.py), (map, origin, arrived), or None: the served one])
        self._superseded: list[tuple[Any, int | None, Any, list[Any]]] = []
        self._out: list[tuple[Origin, wire.Message]] = []  # the dispatcher's answers not yet handed over
        self._conflated: list[tuple[Origin, wire.Message]] = []  # this turn's `conflated` and `overdue` drops, sent after its fills
        self._drop_overdue = self.cfg.overdue == "drop"
        self.prewarm = Prewarm(cfg.prewarm_ms)
        self.stalls = Stalls()  # how late the loop woke (a stopped or starved process), daemon/stalls.py
        self.budget = budgets.Budget()  # hello/control requests per peer (daemon/budget.py)
        self.osc_err_budget = budgets.Budget(OSC_ERRORS_PER_S, OSC_ERRORS_PER_S)  # error answers per OSC source host
        self._osc_in = 0  # bytes of the OSC datagram being handled (its answers may not be larger)
        self._osc_errs: list[tuple[str, str]] | None = None  # errors of the OSC bundle being handled
        self.layouts = Layouts()  # the bundle layouts of the senders (daemon/layout.py)

    # ---- models -----------------------------------------------------------------------------
    def _resolve(self, requested: str | None, sid: str) -> tuple[str, Any]:
        name = requested or self.cfg.stream_models.get(sid) or self.cfg.default_model
        if name not in self.models:
            raise KeyError(f"model {name!r} is not loaded (loaded: {', '.join(sorted(self.models))})")
        return name, self.models[name].model

    def _count(self, name: str, sid: str | None) -> None:
        self.metrics.inc(name)

    # ---- start ------------------------------------------------------------------------------
    def start(self) -> None:
        table, errors = load_all(self.cfg, progress=lambda ev, f: self.log("info", ev, **f))
        if errors:
            raise config_mod.ConfigError("; ".join(f"model {n}: {e}" for n, e in errors.items()))
        self._install(table)
        self.reloader = Reloader(self._reload_work, self._reload_started)
        # the log object changes on reload (level): look it up at each call
        self.net = Transports(self.cfg, self._handle, self._refuse, self.metrics, lambda *a, **k: self.log(*a, **k),
                              self._batch)
        self.net.open()
        if self.cfg.metrics_http:
            self.http = MetricsHTTP(self.cfg.metrics_http[0], self.cfg.metrics_http[1], lambda: self._prom,
                                    allow=self.cfg.metrics_networks, view=in_daemon.from_config(self.cfg, self.models))
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
        try:
            while True:
                ready, arrived = self._wait()  # (daemon/wait.py)
                self.turn(self.clock(), ready, arrived=arrived)
                if self.flag_stop:
                    break
            self._drain()
        finally:
            self.close()

    def turn(self, now: float, ready: Any = None, items: list[tuple[bytes, Origin, float]] | None = None,
             arrived: float | None = None) -> int:
        """One turn of the loop at ``now`` (the daemon's clock): read what ``ready`` (a poll's
        answer) says is waiting, or take ``items`` (bytes, origin, receipt time) as if read;
        decode and hand them to their sessions; serve the frames waiting; answer the frames a
        newer one superseded; send the turn's answers together; then, unless a stop was asked,
        a finished reload is swapped in and housekeeping (idle expiry, metrics) runs when due.
        ``arrived``: the receipt time of everything ``ready`` has (the start of a rehearsal it
        waited through, daemon/wait.py), else each message's is taken as it is read; both on
        the transport's clock, time.perf_counter, the default ``clock``.  Returns how many
        frames were set aside as superseded.  Nothing here raises: a failure is logged,
        counted, and the frames it stranded are answered with an error."""
        net = self.net
        if net is not None:
            net.hold()  # this turn's answers go out together, after its work
        aside = 0
        try:
            if ready and net is not None:
                net.receive(ready, arrived)  # (-> _batch)
            if items:
                self._batch(items)
            aside = sum(len(item) if type(item) is list else 1  # (a run of kept heads: daemon/aside.py)
                        for *_, chain in self._superseded for item in chain if item is not None)
            self._serve()
            if self._superseded or self._conflated:
                self._send_held()  # what came since the fills (they are out already)
                self._answer_superseded()
        except Exception as e:  # noqa: BLE001 - never let a bug end the service: log, count, go on
            self.metrics.inc("internal_errors")
            self.log("error", "internal_error", where="loop", error=f"{type(e).__name__}: {e}"[:300])
            self._abandon_pending(f"{type(e).__name__} while serving")
        finally:
            self._send_held(hold_on=False)
        if self.flag_stop:
            return aside
        try:  # (a failure here, a thread or a resource, must not end the daemon either)
            if self.flag_reload:
                self.flag_reload = False
                self._start_reload(None)
            done = self.reloader.poll() if self.reloader is not None else None
            if done is not None:
                try:
                    self._finish_reload(*done)
                finally:
                    self.reloader.kick()  # type: ignore[union-attr]
            if now >= self._next_house:
                self._next_house = now + HOUSEKEEPING_S
                self._housekeeping(now)
        except Exception as e:  # noqa: BLE001 - the loop goes on
            self.metrics.inc("internal_errors")
            self.log("error", "internal_error", where="housekeeping", error=f"{type(e).__name__}: {e}"[:300])
        return aside

    # ---- output -----------------------------------------------------------------------------
    def _batch(self, items: list[tuple[bytes, Origin, float]]) -> None:
        """What the transport read (its ``on_batch``): the dispatcher's answers handed to the
        transport, the frames taken so far served between two slices of a long burst."""
        if len(items) < BATCH_MIN:  # (dispatch_few, inline: a live stream's turn is most often one frame)
            for data, origin, arrived in items:
                self._take_bytes(data, origin, arrived)
            if self._out:  # (a frame taken has no answer yet)
                out, self._out = self._out, []
                for o, m in out:
                    self._send(o, m)
            return
        gen = self.dispatch(items)
        while True:
            try:
                answers = next(gen)
            except StopIteration as done:
                self._deliver(done.value)
                return
            self._deliver(answers)
            self._serve()

    def _handle(self, data: bytes, origin: Origin, arrived: float) -> None:
        """One message as :meth:`_batch` takes a turn's (the transport's ``on_message``)."""
        self._take_bytes(data, origin, arrived)
        if self._out:
            out, self._out = self._out, []
            for o, m in out:
                self._send(o, m)

    def _answer_superseded(self) -> None:
        """After the turn's fills: its drops, and the answers to the frames set aside."""
        self._deliver(self.superseded_answers())

    def _refuse(self, origin: Origin | None, reason: str, detail: str, sid: str | None, seq: int | None) -> None:
        """A refusal answered at once (the transport's own, a fill that cannot be encoded)."""
        self._reject(origin, reason, detail, sid, seq)
        self._deliver(self._take_out())

    def _deliver(self, answers: list[tuple[Origin, wire.Message]]) -> None:
        for origin, msg in answers:
            self._send(origin, msg)

    def _send(self, origin: Origin, msg: wire.Message, publish: bool = False) -> None:
        if self.net is not None:
            self.net.send(origin, msg, publish)

    def _send_fills(self, origin: Origin, maps: list[dict[str, Any]]) -> None:
        """A bundle's fills as maps (daemon/tickblock.py): what :meth:`_send` of each does."""
        if self.net is not None:
            self.net.send_fill_maps(origin, maps)

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
        collect_old()

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
    settle()
    d.run()
    return 0


def settle() -> None:
    """Between start and the first frame: what the loop's first turns would otherwise do
    in the middle of serving.  The housekeeping's percentiles (status, the systemd status
    line) are first computed 0.5 s after the first frames, and numpy's first ``percentile``
    imports ``numpy.ma`` (3 modules, 12-20 ms live, the turn's bundles then conflated:
    bench/notebook/floor-7.md); computed once here, on a throwaway table, the import happens
    before any frame.  Then everything loaded so far, which lives as long as the daemon, is
    kept out of the collector's generations so the cyclic GC has less to walk mid-frame; and
    the automatic collections stop at generation 1 from now on: a full one (it walks every
    object not frozen) would otherwise run inside whichever turn allocated past the threshold,
    a performer's hello in the middle of the others' frames, say.  Housekeeping runs it instead
    (:func:`collect_old`), after a turn's answers went out, as often as CPython would at most,
    so cyclic garbage that reaches the oldest generation is still reclaimed."""
    m = Metrics()
    m.latencies(0.001, 2)
    m.step_time(0.001)
    m.latency_summary()
    m.step_summary()
    gc.collect()
    gc.freeze()
    t0, t1, _ = gc.get_threshold()
    gc.set_threshold(t0, t1, GEN2_HELD)


def collect_old() -> bool:
    """Housekeeping's full collection, once GEN2_EVERY gen-1 collections ran since the last
    (only when :func:`settle` holds the automatic ones back).  True when it ran."""
    if gc.get_threshold()[2] < GEN2_HELD or gc.get_count()[2] < GEN2_EVERY:
        return False
    gc.collect()
    return True
