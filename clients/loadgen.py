"""Drive N streams at R Hz against a daemon and time every frame's round trip.

One thread, one DEALER per stream (as N capture plugins would have), one ``zmq.Poller``.  Frame
k of every stream is due at ``t0 + k / R`` (absolute deadlines from ``perf_counter``, so the
pace never drifts however late one tick was); between deadlines the loop polls for answers.
The poll sleeps in whole milliseconds and spins the last fraction, so ticks go out within
about 0.1 ms of their deadline without burning a core.  With ``busy`` it never sleeps: a
plugin that spins on its socket sees an answer as soon as it lands, without the kernel's
wake-up delay (0.3-1 ms on a virtual machine) in its round trip; pair it with the daemon's
``busy_poll_ms`` to measure the path without either side's wake-up.

Messages are built and read with msgpack directly in the hot loop (the wire schema's own map
layout, angle/mask bytes precomputed once per take frame), because ``wire.encode``/``decode``
validate every field and the generator must not become the bottleneck it is measuring; the
handshake goes through ``daemon.wire``.

Each frame's round trip runs from just before its ``send`` to just after its answer was read;
with many streams an answer may wait while the loop sends the rest of a tick, and that wait
is part of the figure (a real plugin in one process would see it too).
"""
from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np
import zmq

from clients.control import decode_reply
from clients.session import DEFAULT_TIMEOUT_S, dealer_socket
from daemon import wire

DRAIN_S = 10.0  # after the last tick, wait up to this long for every outstanding answer (an overloaded
# daemon answers each frame eventually, with a fill or a drop; counts are compared only then)
HANDSHAKE_TIMEOUT_S = 5.0
PROGRESS_EVERY_S = 2.0


@dataclass
class LoadResult:
    """Per-frame outcome of one run.

    rtt_ms : (n_served,) round trips of served frames, milliseconds.
    proc_us : (n_served,) the daemon's own processing time of each, microseconds.
    lateness_ms : (n_ticks,) how late each tick's first send was after its deadline.
    """

    streams: list[str]
    rate: float
    seconds: float
    sent: int = 0
    served: int = 0
    degraded: int = 0
    passthrough: int = 0
    dropped: int = 0
    errors: int = 0
    unsent: int = 0
    drop_reasons: dict[str, int] = field(default_factory=dict)
    error_reasons: dict[str, int] = field(default_factory=dict)
    rtt_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    proc_us: np.ndarray = field(default_factory=lambda: np.zeros(0))
    lateness_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    wall_s: float = 0.0
    cpu_s: float = 0.0  # this process's CPU time over the run
    in_flight: np.ndarray | None = None  # unanswered frames per stream (with max_in_flight)

    @property
    def lost(self) -> int:
        """Frames sent that got no answer at all before the drain ended."""
        return self.sent - self.served - self.dropped - self.errors

    @property
    def rtt_s(self) -> np.ndarray:
        """The round trips in seconds."""
        return self.rtt_ms / 1000.0

    def summary(self) -> dict[str, Any]:
        """Percentiles (ms, rounded) and counts as one flat map, for a table row or JSON."""
        p = {k: (None if v is None else round(v, 4)) for k, v in percentiles(self.rtt_ms).items()}
        proc = {"daemon_proc_p50_ms": round(float(np.median(self.proc_us)) / 1e3, 4) if self.proc_us.size else None,
                "daemon_proc_p99_ms": (round(float(np.percentile(self.proc_us, 99)) / 1e3, 4)
                                       if self.proc_us.size else None)}
        return {**p, "served": self.served, "degraded": self.degraded, "dropped": self.dropped, "errors": self.errors,
                "lost": self.lost, "unsent": self.unsent, "sent": self.sent, "seconds": round(self.wall_s, 3), **proc}


def percentiles(rtt_ms: np.ndarray) -> dict[str, float | None]:
    if rtt_ms.size == 0:
        return {k: None for k in ("p50_ms", "p90_ms", "p99_ms", "p999_ms", "max_ms")}
    q = np.percentile(rtt_ms, [50, 90, 99, 99.9])
    return {"p50_ms": float(q[0]), "p90_ms": float(q[1]), "p99_ms": float(q[2]), "p999_ms": float(q[3]),
            "max_ms": float(rtt_ms.max())}


def make_frames(n_frames: int, n_channels: int, missing: np.ndarray | None, rng: np.random.Generator,
                source: np.ndarray | None = None) -> np.ndarray:
    """(n_frames, n_channels) float32 frames; ``source`` rows are cycled if given (real motion),
    otherwise smooth sinusoids.  ``missing``: (n_channels,) bool set to NaN in every frame."""
    if source is not None:
        f = source[np.arange(n_frames) % source.shape[0]].astype(np.float32)
    else:
        t = np.arange(n_frames)[:, None] / 120.0
        ph = rng.uniform(0, 2 * np.pi, n_channels)[None]
        f = (30.0 * np.sin(2 * np.pi * 0.9 * t + ph)).astype(np.float32)
    if missing is not None:
        f[:, missing] = np.nan
    out: np.ndarray = f
    return out


def run_load(endpoint: str, channels: list[str] | None, frames: np.ndarray, observed: np.ndarray | None = None, *,
             n_streams: int, rate: float, seconds: float, model: str | None = None, prefix: str = "bench",
             progress: bool = True, busy: bool = False, connections: int | None = None,
             bundle: bool = False, warmup_s: float = 0.0, max_in_flight: int | None = None,
             drain_s: float = DRAIN_S) -> LoadResult:
    """Offer ``n_streams`` x ``rate`` frames/s for ``seconds``; every stream replays ``frames``
    (T, C) with mask ``observed`` (T, C) from its own starting offset, cycling.

    ``connections``: how many DEALER sockets carry the streams (stream i on socket
    ``i % connections``).  The default, one per stream, is N separate capture plugins; one
    connection is one capture system sending every performer's stream down one socket.

    ``bundle``: each connection sends its streams' frames of a tick as one ``frames`` message
    (and reads their answers from ``replies``), as a capture system that tracks several
    performers has them: one capture instant, one message.

    ``channels`` None sends no handshake (the streams get the daemon's default model, any
    width); ``observed`` None means every finite value of ``frames`` was captured.  The first
    ``warmup_s`` seconds are sent but neither counted nor timed.  ``max_in_flight``: a stream
    with that many unanswered frames skips its next one (counted ``unsent``), as a plugin that
    must not queue without bound would."""
    connections = n_streams if connections is None else connections
    if n_streams < 1 or rate <= 0 or seconds <= 0 or not 1 <= connections <= n_streams:
        raise ValueError(f"need streams >= 1, rate > 0, seconds > 0, 1 <= connections <= streams "
                         f"(got {n_streams}, {rate}, {seconds}, {connections})")
    if max_in_flight is not None and bundle:
        raise ValueError("max_in_flight is per stream; a bundle sends every stream of its connection at once")
    T, C = frames.shape
    if observed is None:
        observed = np.isfinite(frames)
    if (channels is not None and C != len(channels)) or observed.shape != frames.shape:
        raise ValueError(f"frames {frames.shape} / observed {observed.shape} do not match {channels and len(channels)} "
                         f"channels")
    given = np.where(observed, frames, np.nan).astype(wire.F32)
    angle_bytes = [given[j].tobytes() for j in range(T)]
    mask_bytes = [observed[j].astype(np.uint8).tobytes() for j in range(T)]
    pack = msgpack.Packer(use_bin_type=True).pack
    warm = int(round(warmup_s * rate))
    n_ticks = warm + max(1, int(round(seconds * rate)))
    ids = [f"{prefix}-{i:03d}" for i in range(n_streams)]
    res = LoadResult(ids, rate, seconds)
    ctx = zmq.Context()
    conns = [dealer_socket(ctx, endpoint, DEFAULT_TIMEOUT_S) for _ in range(connections)]
    socks = [conns[i % connections] for i in range(n_streams)]
    if bundle:  # one message per connection and tick, carrying the rows (streams) of that connection
        senders, members = conns, [list(range(c, n_streams, connections)) for c in range(connections)]
    else:
        senders, members = socks, [[i] for i in range(n_streams)]
    index = {sid: i for i, sid in enumerate(ids)}   # answers name their stream: that finds the row
    poller = zmq.Poller()
    for s in conns:
        poller.register(s, zmq.POLLIN)
    send_t = np.full((n_streams, n_ticks), np.nan)
    rtt = np.full((n_streams, n_ticks), np.nan)
    proc = np.full((n_streams, n_ticks), np.nan)
    lateness = np.zeros(n_ticks)
    res.in_flight = np.zeros(n_streams, np.int64) if max_in_flight is not None else None
    cpu0 = time.process_time()
    try:
        if channels is not None:
            _handshake(socks, ids, channels, model)
        offsets = (np.arange(n_streams) * (T // max(1, n_streams))) % T
        # header bytes are constant per stream; the frame body is built per send (seq, t, angles)
        t0 = time.perf_counter() + 0.05
        next_report = t0 + PROGRESS_EVERY_S
        wall0 = time.time() - time.perf_counter()       # perf_counter -> wall clock, for the capture stamps
        for k in range(n_ticks):
            due = t0 + k / rate
            # the tick's messages are built before its deadline, as a capture system has its frames
            # ready when it sends them: the burst of sends is then only sends
            maps = [{"v": wire.SCHEMA_VERSION, "type": "frame", "stream": ids[i], "seq": k, "t": wall0 + due,
                     "angles": angle_bytes[(offsets[i] + k) % T], "observed": mask_bytes[(offsets[i] + k) % T]}
                    for i in range(n_streams)]
            if bundle:
                for mp in maps:
                    del mp["v"], mp["type"]  # implied by the bundle
                bodies = [pack({"v": wire.SCHEMA_VERSION, "type": "frames", "frames": [maps[i] for i in rows]})
                          for rows in members]
            else:
                bodies = [pack(mp) for mp in maps]
            _wait_until(due, poller, index, send_t, rtt, proc, res, busy)
            now = time.perf_counter()
            lateness[k] = (now - due) * 1000.0
            measured = k >= warm
            for j, s in enumerate(senders):
                body = bodies[j]
                rows = members[j]
                if res.in_flight is not None and res.in_flight[j] >= max_in_flight:
                    res.unsent += len(rows) * measured
                    continue
                t = time.perf_counter()
                try:
                    s.send(body, zmq.NOBLOCK, copy=False)
                except zmq.Again:
                    res.unsent += len(rows) * measured
                    continue
                if res.in_flight is not None:
                    res.in_flight[j] += 1
                if measured:  # a warm-up frame's answer is read but not counted (its send_t stays NaN)
                    send_t[rows, k] = t
                    res.sent += len(rows)
            if progress and now >= next_report:
                next_report += PROGRESS_EVERY_S
                print(f"\r  bench: {k + 1}/{n_ticks} ticks, {res.served} served, {res.dropped} dropped",
                      end="", file=sys.stderr, flush=True)
        end = time.perf_counter() + drain_s
        while res.served + res.dropped + res.errors < res.sent and time.perf_counter() < end:
            _wait_until(min(end, time.perf_counter() + 0.05), poller, index, send_t, rtt, proc, res, busy)
        res.wall_s = time.perf_counter() - t0
        res.cpu_s = time.process_time() - cpu0
        if progress:
            print(f"\r  bench: {n_ticks}/{n_ticks} ticks, {res.served} served, {res.dropped} dropped   ",
                  file=sys.stderr, flush=True)
    finally:
        for s in conns:
            s.close(linger=0)
        ctx.term()
    ok = np.isfinite(rtt)
    res.rtt_ms = rtt[ok]
    res.proc_us = proc[ok]
    res.lateness_ms = lateness
    return res


def _handshake(socks: list[zmq.Socket[Any]], ids: list[str], channels: list[str], model: str | None) -> None:
    for s, sid in zip(socks, ids):
        s.send(wire.encode(wire.Hello(sid, channels, model)))
    waiting: dict[zmq.Socket[Any], int] = {}  # socket -> how many acks it still owes
    for s in socks:
        waiting[s] = waiting.get(s, 0) + 1
    for s, n in waiting.items():
        for _ in range(n):
            if not s.poll(int(HANDSHAKE_TIMEOUT_S * 1000), zmq.POLLIN):
                raise TimeoutError(f"a hello-ack is missing after {HANDSHAKE_TIMEOUT_S:g} s")
            msg = decode_reply(s.recv())
            if isinstance(msg, wire.ErrorMsg):
                raise ValueError(f"daemon refused the handshake of {msg.stream}: {msg.reason}: {msg.detail}")


def _wait_until(deadline: float, poller: zmq.Poller, index: dict[Any, int], send_t: np.ndarray, rtt: np.ndarray,
                proc: np.ndarray, res: LoadResult, busy: bool = False) -> None:
    while True:
        left = deadline - time.perf_counter()
        if left <= 0:
            return
        # sleep whole milliseconds in the poll, spin the remainder (ms-resolution poll timeout)
        ms = 0 if busy else int(left * 1000.0 - 0.3)
        got = poller.poll(ms if ms > 0 else 0)
        if busy and not got:
            os.sched_yield()  # let ZeroMQ's I/O thread run on this core at once
        for sock, _ in got:
            # stamp every waiting answer as it is read, and only then decode them: reading one
            # answer must not wait for the decoding of the answers before it
            arrived = []
            while True:
                try:
                    arrived.append((sock.recv(zmq.NOBLOCK), time.perf_counter()))
                except zmq.Again:
                    break
            for data, t in arrived:
                _account(data, index, t, send_t, rtt, proc, res)


def _account(data: bytes, index: dict[str, int], t: float, send_t: np.ndarray, rtt: np.ndarray, proc: np.ndarray,
             res: LoadResult) -> None:
    """Count one answer.  Reads only the fields it needs; anything unreadable counts as an error."""
    try:
        m = msgpack.unpackb(data, raw=False)
        typ = m["type"]
        if typ == "replies":  # the answers to a bundle, read as if they had come one by one
            for r in m["replies"]:
                _count(r, r["type"], index, t, send_t, rtt, proc, res)
            return
    except Exception:  # noqa: BLE001 - a malformed answer is counted, never fatal to the run
        res.errors += 1
        res.error_reasons["unreadable"] = res.error_reasons.get("unreadable", 0) + 1
        return
    _count(m, typ, index, t, send_t, rtt, proc, res)


def _count(m: dict[str, Any], typ: str, index: dict[str, int], t: float, send_t: np.ndarray, rtt: np.ndarray,
           proc: np.ndarray, res: LoadResult) -> None:
    """Count one answer to a measured frame (an answer to a warm-up frame, whose send time is
    NaN, is read and not counted; an error naming no frame is counted)."""
    k = m.get("seq", -1)
    i = index.get(m.get("stream"), -1)  # type: ignore[arg-type]
    known = i >= 0 and isinstance(k, int) and 0 <= k < send_t.shape[1]
    if known and res.in_flight is not None and typ in ("fill", "drop", "error"):
        res.in_flight[i] -= 1
    measured = known and send_t[i, k] == send_t[i, k]  # sent while measuring (not NaN)
    if typ == "fill":
        if not measured:
            return
        rtt[i, k] = (t - send_t[i, k]) * 1000.0
        proc[i, k] = m.get("proc_us", np.nan)
        res.served += 1
        st = m.get("status")
        if st == "degraded":
            res.degraded += 1
        elif st == "passthrough":
            res.passthrough += 1
    elif typ == "drop":
        if not measured:
            return
        res.dropped += 1
        r = str(m.get("reason"))
        res.drop_reasons[r] = res.drop_reasons.get(r, 0) + 1
    else:
        if known and not measured:
            return
        res.errors += 1
        r = str(m.get("reason", typ))
        res.error_reasons[r] = res.error_reasons.get(r, 0) + 1
