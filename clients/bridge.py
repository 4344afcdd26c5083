"""``lacuna bridge``: an inline relay for capture systems that speak OSC.

    capture system --OSC/UDP--> bridge --ZeroMQ req/reply--> lacuna serve
                                  |
                                  +--OSC/UDP (and/or ZeroMQ PUB)--> rest of the pipeline

The capture system sends the daemon's own OSC input addresses (``/lacuna/hello``,
``/lacuna/frame``, ``/lacuna/frame/masked``, ``/lacuna/reset``; docs/PROTOCOL.md); the bridge
fills every frame through the daemon and re-emits the answer in the daemon's OSC output form
(one bundle per frame: ``/lacuna/fill``, ``/lacuna/std``, ``/lacuna/filled`` ...) and/or as a
wire ``fill`` on a ZeroMQ PUB (topic = stream id).

When the daemon is gone (no answer within ``timeout_s``), the frame is passed through unfilled
at once, flagged ``status = "passthrough"`` with model ``""`` and nothing marked filled, so
the pipeline never stalls.  While the daemon stays away, frames pass through without waiting
and the daemon is probed again every ``probe_s``; when it answers, filling resumes (the client
re-sends each stream's handshake).  The bridge is one thread and one loop: nothing sleeps in
the path of a frame.
"""
from __future__ import annotations

import select
import socket
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import zmq

from clients.client import Client
from clients.recording import RecordingWriter
from clients.session import DaemonRefused, DaemonUnavailable
from daemon import osc, wire

DEFAULT_TIMEOUT_S = 0.02  # a frame waits at most this for the daemon before it passes through
DEFAULT_PROBE_S = 1.0  # while the daemon is away, try it again this often
POLL_S = 0.2  # the loop wakes up this often to look at the stop flag


@dataclass
class BridgeCounts:
    frames: int = 0
    filled: int = 0
    passed_through: int = 0
    dropped: int = 0
    rejected: int = 0


class Bridge:
    """OSC in, daemon in the middle, OSC and/or ZeroMQ PUB out.

    Parameters
    ----------
    endpoint : the daemon's ROUTER.
    listen : (host, port) to receive OSC on (port 0 = any free one; see ``.address``).
    send : (host, port) to send filled OSC to, or None.
    pub : ZeroMQ endpoint to bind a PUB on, or None.
    record : a path template for recordings of raw and filled frames, ``{stream}`` replaced.
    """

    def __init__(self, endpoint: str, listen: tuple[str, int] = ("127.0.0.1", 9001),
                 send: tuple[str, int] | None = None, pub: str | None = None, *,
                 timeout_s: float = DEFAULT_TIMEOUT_S, probe_s: float = DEFAULT_PROBE_S,
                 record: str | None = None, log: Callable[[str], None] | None = None):
        if send is None and pub is None:
            raise ValueError("the bridge needs somewhere to send filled frames (--send HOST:PORT and/or --pub ENDPOINT)")
        self.endpoint = endpoint
        self.timeout_s = timeout_s
        self.probe_s = probe_s
        self.send_addr = send
        self.ctx = zmq.Context()
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.udp.bind(listen)
        self.address = self.udp.getsockname()
        self.out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.pub: zmq.Socket[Any] | None = None
        if pub:
            self.pub = self.ctx.socket(zmq.PUB)
            self.pub.setsockopt(zmq.LINGER, 0)
            self.pub.bind(pub)
        self.clients: dict[str, Client] = {}
        self.record = record
        self.writers: dict[str, RecordingWriter] = {}
        self.down_until = 0.0  # perf_counter time before which the daemon is taken to be away
        self.daemon_up = True
        self.counts = BridgeCounts()
        self.stop_flag = False
        self.log = log or (lambda s: print(f"lacuna bridge: {s}", file=sys.stderr, flush=True))

    # ---- one datagram ----------------------------------------------------------------------
    def handle(self, data: bytes) -> list[wire.Message]:
        """Decode one OSC datagram (a message, or a bundle of them: each handled as if it had
        come alone, in order), fill it through the daemon, emit and return the answers."""
        try:
            msgs: list[wire.Message | wire.WireError] = (osc.decode_bundle(data) if data.startswith(osc.BUNDLE_PREFIX)
                                                         else [osc.decode(data)])
        except wire.WireError as e:
            msgs = [e]
        out: list[wire.Message] = []
        for m in msgs:
            out += self._one(m)
        return out

    def _one(self, msg: wire.Message | wire.WireError) -> list[wire.Message]:
        if isinstance(msg, wire.WireError):
            self.counts.rejected += 1
            out: list[wire.Message] = [wire.error_for(msg)]
            self._emit(out)
            return out
        if isinstance(msg, wire.Hello):
            out = self._hello(msg)
        elif isinstance(msg, wire.Frame):
            out = [self._frame(msg)]
        elif isinstance(msg, wire.Control) and msg.cmd == "reset":
            c = self.clients.pop(msg.stream or "", None)
            if c is not None:
                c.close()
            out = []
        else:
            out = []
        self._emit(out)
        return out

    def _client(self, sid: str, channels: list[str] | None = None, model: str | None = None) -> Client:
        c = self.clients.get(sid)
        if c is None or channels is not None:
            if c is not None:
                c.close()
            c = Client(self.endpoint, sid, channels, model, timeout_s=self.timeout_s, retries=0, ctx=self.ctx)
            self.clients[sid] = c
        return c

    def _daemon_away(self) -> bool:
        return not self.daemon_up and time.perf_counter() < self.down_until

    def _mark(self, up: bool) -> None:
        if up != self.daemon_up:
            self.log("daemon answering again: filling resumed" if up else
                     f"daemon not answering within {self.timeout_s * 1000:g} ms: passing frames through (flagged)")
        self.daemon_up = up
        if not up:
            self.down_until = time.perf_counter() + self.probe_s

    def _hello(self, h: wire.Hello) -> list[wire.Message]:
        c = self._client(h.stream, h.channels, h.model)
        if self._daemon_away():
            return []
        try:
            ack = c.hello()
        except DaemonUnavailable:
            self._mark(False)
            return []
        except DaemonRefused as e:
            return [e.error]
        self._mark(True)
        return [ack]

    def _frame(self, f: wire.Frame) -> wire.Message:
        self.counts.frames += 1
        c = self._client(f.stream)
        angles = np.asarray(f.angles, dtype=np.float64)
        observed = f.observed if f.observed is not None else np.isfinite(angles)
        if c.session.channels is not None and len(angles) != len(c.session.channels):
            self.counts.rejected += 1
            return wire.ErrorMsg("width", f"frame has {len(angles)} values, stream {f.stream!r} said "
                                          f"{len(c.session.channels)} channels", f.stream, f.seq)
        reply: wire.Message | None = None
        if not self._daemon_away():
            try:
                reply = c.fill(angles, observed, t=f.t, seq=f.seq)
                self._mark(True)
            except DaemonUnavailable:
                self._mark(False)
            except DaemonRefused as e:
                self.counts.rejected += 1
                return e.error
        if reply is None:
            reply = passthrough(f, angles, observed)
            self.counts.passed_through += 1
        elif isinstance(reply, wire.Drop):
            self.counts.dropped += 1
        else:
            self.counts.filled += 1
        if self.record and isinstance(reply, wire.FillMsg):
            self._writer(f.stream, len(angles)).write(f.seq, f.t, angles, observed, reply)
        return reply

    def _writer(self, sid: str, n: int) -> RecordingWriter:
        w = self.writers.get(sid)
        if w is None:
            c = self.clients[sid]
            names = c.session.channels or [f"ch{i}" for i in range(n)]
            path = self.record.replace("{stream}", sid) if self.record else ""
            w = self.writers[sid] = RecordingWriter(path, names, None, sid, "lacuna bridge")
        return w

    def _emit(self, msgs: list[wire.Message]) -> None:
        for m in msgs:
            if self.send_addr is not None:
                try:
                    self.out.sendto(osc.encode(m), self.send_addr)
                except (TypeError, OSError) as e:
                    self.log(f"cannot send OSC to {self.send_addr}: {e}")
            if self.pub is not None and isinstance(m, (wire.FillMsg, wire.HelloAck, wire.Drop)):
                self.pub.send_multipart([m.stream.encode(), wire.encode(m)])

    # ---- loop ------------------------------------------------------------------------------
    def serve_forever(self) -> None:
        """Run until ``stop_flag`` is set (a signal handler sets it)."""
        while not self.stop_flag:
            r, _, _ = select.select([self.udp], [], [], POLL_S)
            if not r:
                continue
            data, _addr = self.udp.recvfrom(1 << 16)
            self.handle(data)

    def close(self) -> None:
        for c in self.clients.values():
            c.close()
        self.clients.clear()
        for w in self.writers.values():
            w.close()
        if self.pub is not None:
            self.pub.close(linger=0)
        self.udp.close()
        self.out.close()
        self.ctx.term()

    def __enter__(self) -> Bridge:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def passthrough(f: wire.Frame, angles: np.ndarray, observed: np.ndarray) -> wire.FillMsg:
    """The frame as it came, flagged: status ``passthrough``, model ``""``, nothing filled."""
    C = len(angles)
    return wire.FillMsg(f.stream, f.seq, f.t, np.where(observed, angles, np.nan).astype(np.float32),
                        np.zeros(C, bool), np.zeros(C, np.float32), "passthrough", "", 0)
