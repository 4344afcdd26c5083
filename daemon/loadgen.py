"""Load generation against a real daemon: the reusable core of the daemon benchmarks and tests.

* :class:`DaemonProcess` starts `python -m lacuna.cli serve --config FILE` as a child process,
  waits for its ``ready`` log line (which carries the bound endpoints, so configs can use
  ``tcp://127.0.0.1:*`` and port 0), collects its JSON log, and kills it on exit (never hangs).
* :func:`run_load` drives N streams at R Hz over request/reply (one DEALER socket per stream,
  like N capture plugins) and returns every frame's round-trip time and the answers' counts.

The clients package's `lacuna bench` can import both; they only use the public wire schema.
"""
from __future__ import annotations

import json
import os
import queue
import signal as _signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np
import zmq

from daemon import wire

READY_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 10.0


class DaemonProcess:
    """A `lacuna serve` child process.  ``endpoints`` comes from its ready line."""

    def __init__(self, config_path: str, env: dict[str, str] | None = None, python: str = sys.executable):
        self.config_path = config_path
        self.env = {**os.environ, **(env or {})}
        self.python = python
        self.proc: subprocess.Popen | None = None
        self.log: list[dict[str, Any]] = []
        self.raw_stderr: list[str] = []
        self._lines: queue.Queue = queue.Queue()
        self.endpoints: dict[str, Any] = {}

    def start(self, timeout_s: float = READY_TIMEOUT_S) -> "DaemonProcess":
        self.proc = subprocess.Popen([self.python, "-m", "lacuna.cli", "serve", "--config", self.config_path],
                                     stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                     env=self.env, text=True)
        threading.Thread(target=self._read, daemon=True).start()
        rec = self.wait_for("ready", timeout_s)
        self.endpoints = rec["endpoints"]
        return self

    def _read(self) -> None:
        assert self.proc is not None and self.proc.stderr is not None
        for line in self.proc.stderr:
            self.raw_stderr.append(line)
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            self.log.append(rec)
            self._lines.put(rec)
        self._lines.put(None)

    def wait_for(self, event: str, timeout_s: float = 10.0, **match: Any) -> dict[str, Any]:
        """Next log record with this event (and matching fields); raises on timeout or exit."""
        for rec in self.log:
            if rec.get("event") == event and all(rec.get(k) == v for k, v in match.items()) and not rec.get("_seen"):
                rec["_seen"] = True
                return rec
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"daemon did not log {event!r} within {timeout_s} s; stderr:\n{''.join(self.raw_stderr[-20:])}")
            try:
                rec = self._lines.get(timeout=left)
            except queue.Empty:
                continue
            if rec is None:
                raise RuntimeError(f"daemon exited ({self.proc.poll() if self.proc else '?'}) before logging {event!r}; "
                                   f"stderr:\n{''.join(self.raw_stderr[-20:])}")
            if rec.get("event") == event and all(rec.get(k) == v for k, v in match.items()):
                rec["_seen"] = True
                return rec

    def signal(self, sig: int) -> None:
        assert self.proc is not None
        self.proc.send_signal(sig)

    def stop(self, sig: int = _signal.SIGTERM, timeout_s: float = STOP_TIMEOUT_S) -> int:
        """Signal, wait, kill if needed; returns the exit status."""
        if self.proc is None:
            return 0
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        return self.proc.returncode

    def __enter__(self) -> "DaemonProcess":
        return self.start() if self.proc is None else self

    def __exit__(self, *exc: Any) -> None:
        self.stop()


@dataclass
class LoadResult:
    rtt_s: list[float] = field(default_factory=list)  # round trip of every served frame
    proc_us: list[int] = field(default_factory=list)  # the daemon's own processing time
    sent: int = 0
    served: int = 0
    degraded: int = 0
    dropped: int = 0
    errors: int = 0
    lost: int = 0  # requests never answered within the timeout
    unsent: int = 0  # frames the generator could not queue (socket at its high-water mark)
    seconds: float = 0.0
    cpu_s: float = 0.0  # this process's CPU time

    def summary(self) -> dict[str, Any]:
        a = np.asarray(self.rtt_s) * 1e3
        q = np.percentile(a, [50, 90, 99, 99.9]) if a.size else [float("nan")] * 4
        return {"p50_ms": round(float(q[0]), 4), "p90_ms": round(float(q[1]), 4), "p99_ms": round(float(q[2]), 4),
                "p999_ms": round(float(q[3]), 4), "max_ms": round(float(a.max()), 4) if a.size else None,
                "served": self.served, "degraded": self.degraded, "dropped": self.dropped, "errors": self.errors,
                "lost": self.lost, "unsent": self.unsent, "sent": self.sent, "seconds": round(self.seconds, 3),
                "daemon_proc_p50_ms": round(float(np.median(self.proc_us)) / 1e3, 4) if self.proc_us else None,
                "daemon_proc_p99_ms": round(float(np.percentile(self.proc_us, 99)) / 1e3, 4) if self.proc_us else None}


def make_frames(n_frames: int, n_channels: int, missing: np.ndarray | None, rng: np.random.Generator,
                source: np.ndarray | None = None) -> np.ndarray:
    """(n_frames, n_channels) float32 frames; ``source`` rows are cycled if given (real motion),
    otherwise smooth sinusoids.  ``missing``: (n_channels,) bool set to NaN in every frame."""
    if source is not None:
        idx = np.arange(n_frames) % source.shape[0]
        f = source[idx].astype(np.float32)
    else:
        t = np.arange(n_frames)[:, None] / 120.0
        ph = rng.uniform(0, 2 * np.pi, n_channels)[None]
        f = (30.0 * np.sin(2 * np.pi * 0.9 * t + ph)).astype(np.float32)
    if missing is not None:
        f[:, missing] = np.nan
    return f


def run_load(endpoint: str, n_streams: int, rate_hz: float, seconds: float, frames: np.ndarray,
             channels: list[str] | None = None, model: str | None = None, timeout_s: float = 2.0,
             prefix: str = "bench", warmup_s: float = 0.5, max_in_flight: int | None = None) -> LoadResult:
    """Drive ``n_streams`` streams at ``rate_hz`` for ``seconds``, one DEALER per stream.

    Every tick sends one frame on every stream, then reads answers until the next tick.  The
    first ``warmup_s`` seconds are sent but not measured.  frames: (n, C) float32 cycled.
    ``max_in_flight``: a stream with that many unanswered frames skips its next frame (counted
    ``unsent``), as a plugin that must not queue without bound would; None sends regardless.
    """
    ctx = zmq.Context()
    socks = []
    res = LoadResult()
    try:
        for i in range(n_streams):
            s = ctx.socket(zmq.DEALER)
            s.setsockopt(zmq.LINGER, 0)
            s.connect(endpoint)
            socks.append(s)
        sid = [f"{prefix}{i}" for i in range(n_streams)]
        if channels is not None:
            for s, name in zip(socks, sid):
                s.send(wire.encode(wire.Hello(name, channels, model)))
            for s in socks:
                if not s.poll(int(timeout_s * 1000)):
                    raise TimeoutError(f"no hello-ack from {endpoint}")
                ack = wire.decode(s.recv(), 64 << 20)
                if not isinstance(ack, wire.HelloAck):
                    raise ValueError(f"hello refused: {ack}")
        poller = zmq.Poller()
        for s in socks:
            poller.register(s, zmq.POLLIN)
        index = {s: i for i, s in enumerate(socks)}
        sent_at: dict[tuple[int, int], float] = {}
        in_flight = [0] * n_streams
        period = 1.0 / rate_hz
        n_ticks = int(round((seconds + warmup_s) * rate_hz))
        warm_ticks = int(round(warmup_s * rate_hz))
        cpu0 = time.process_time()
        t_start = time.perf_counter()
        nf = frames.shape[0]

        def read(deadline: float) -> None:
            while True:
                left = deadline - time.perf_counter()
                ev = dict(poller.poll(max(0, int(left * 1000)) if left > 0 else 0))
                if not ev:
                    if left <= 0:
                        return
                    continue
                for s in ev:
                    while True:
                        try:
                            data = s.recv(zmq.NOBLOCK)
                        except zmq.Again:
                            break
                        now = time.perf_counter()
                        # the daemon's answers are trusted here: a bare unpack keeps the
                        # generator's own cost (part of every measured round trip) small
                        m = msgpack.unpackb(data, raw=False)
                        i = index[s]
                        typ, seq = m.get("type"), m.get("seq")
                        if typ in ("fill", "drop", "error") and (i, seq) in sent_at:
                            in_flight[i] -= 1
                        if typ == "fill":
                            t0 = sent_at.pop((i, seq), None)
                            if t0 is not None and t0 >= 0:
                                res.rtt_s.append(now - t0)
                                res.proc_us.append(m["proc_us"])
                                res.served += 1
                                res.degraded += m["status"] == "degraded"
                        elif typ == "drop":
                            t0 = sent_at.pop((i, seq), None)
                            res.dropped += t0 is not None and t0 >= 0
                        elif typ == "error":
                            res.errors += 1
                            if seq is not None:
                                sent_at.pop((i, seq), None)

        for k in range(n_ticks):
            tick = t_start + k * period
            measured = k >= warm_ticks
            for i, s in enumerate(socks):
                f = frames[k % nf]
                if max_in_flight is not None and in_flight[i] >= max_in_flight:
                    res.unsent += measured
                    continue
                body = wire.encode(wire.Frame(sid[i], k, tick, f))
                # the clock is read before the send: after it, the kernel may hand the CPU to
                # the daemon woken by this very frame, and a later reading would hide its work
                t0 = time.perf_counter()
                try:  # never block the generator: a full queue is counted, like a dropped frame
                    s.send(body, zmq.NOBLOCK, copy=False)
                except zmq.Again:
                    res.unsent += measured
                    continue
                sent_at[(i, k)] = t0 if measured else -1.0
                in_flight[i] += 1
                res.sent += measured
            read(t_start + (k + 1) * period)
        read(time.perf_counter() + timeout_s if sent_at else time.perf_counter())
        res.lost = sum(1 for v in sent_at.values() if v >= 0)
        res.seconds = time.perf_counter() - t_start
        res.cpu_s = time.process_time() - cpu0
        return res
    finally:
        for s in socks:
            s.close(0)
        ctx.term()
