"""Transports: the daemon's sockets (ZeroMQ ROUTER/PULL/SUB/PUB, OSC over UDP) behind one poller.

``receive(ready)`` drains what arrived (bounded per socket and tick) and hands each message to
``on_message(bytes, origin, arrival time)``; ``send(origin, message, publish)`` answers on the
transport the message came from and, for filled frames, also publishes on PUB.  Sends never
block: a peer over its high-water mark loses that answer and the loss is counted.
"""
from __future__ import annotations

import errno
import socket
import time
from typing import Any, Callable

import zmq

from daemon import osc, wire
from daemon.config import Config
from daemon.metrics import Metrics
from daemon.session import Origin

DRAIN_MAX = 2048  # messages read per socket per tick: keeps one busy socket from starving the rest
UDP_MAX = 65535  # bytes
ZMQ_MAXMSG_FLOOR = 1 << 20  # bytes


class Transports:
    def __init__(self, cfg: Config, on_message: Callable[[bytes, Origin, float], None],
                 on_reject: Callable[..., None], metrics: Metrics, log: Callable[..., None]):
        self.cfg = cfg
        self.on_message = on_message
        self.on_reject = on_reject
        self.metrics = metrics
        self.log = log
        self.ctx: zmq.Context | None = None
        self.router: zmq.Socket | None = None
        self.pull: zmq.Socket | None = None
        self.sub: zmq.Socket | None = None
        self.pub: zmq.Socket | None = None
        self.udp: socket.socket | None = None
        self.poller = zmq.Poller()

    def _sock(self, kind: int) -> zmq.Socket:
        assert self.ctx is not None
        c = self.cfg
        s = self.ctx.socket(kind)
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.SNDHWM, c.zmq_hwm)
        s.setsockopt(zmq.RCVHWM, c.zmq_hwm)
        # beyond this ZeroMQ disconnects the peer without reading the message into memory;
        # between max_message_bytes and this the daemon reads it and answers `too_large`
        s.setsockopt(zmq.MAXMSGSIZE, max(ZMQ_MAXMSG_FLOOR, 4 * c.max_message_bytes))
        return s

    def open(self) -> None:
        """Bind/connect everything the config names.  Raises zmq.ZMQError/OSError naming the address."""
        c = self.cfg
        self.ctx = zmq.Context()
        try:
            if c.zmq_router:
                self.router = self._sock(zmq.ROUTER)
                # an answer that cannot be queued (peer gone, or not reading: at its high-water
                # mark) raises instead of vanishing silently, so it is counted
                self.router.setsockopt(zmq.ROUTER_MANDATORY, 1)
                _bind(self.router, c.zmq_router, "zmq.router")
                self.poller.register(self.router, zmq.POLLIN)
            if c.zmq_pull:
                self.pull = self._sock(zmq.PULL)
                _bind(self.pull, c.zmq_pull, "zmq.pull")
                self.poller.register(self.pull, zmq.POLLIN)
            if c.zmq_sub:
                self.sub = self._sock(zmq.SUB)
                self.sub.setsockopt(zmq.SUBSCRIBE, b"")
                for ep in c.zmq_sub:
                    self.sub.connect(ep)
                self.poller.register(self.sub, zmq.POLLIN)
            if c.zmq_pub:
                self.pub = self._sock(zmq.PUB)
                _bind(self.pub, c.zmq_pub, "zmq.pub")
            if c.osc_listen:
                fam = socket.AF_INET6 if ":" in c.osc_listen[0] else socket.AF_INET
                self.udp = socket.socket(fam, socket.SOCK_DGRAM)
                try:
                    self.udp.bind(c.osc_listen)
                except OSError as e:
                    raise OSError(f"osc.listen {c.osc_listen[0]}:{c.osc_listen[1]}: cannot bind ({e.strerror or e})") from None
                self.udp.setblocking(False)
                self.poller.register(self.udp.fileno(), zmq.POLLIN)
        except BaseException:
            self.close(0)
            raise

    def endpoints(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for name, s in (("router", self.router), ("pull", self.pull), ("pub", self.pub)):
            if s is not None:
                out[name] = s.getsockopt(zmq.LAST_ENDPOINT).decode()
        if self.sub is not None:
            out["sub"] = self.cfg.zmq_sub
        if self.udp is not None:
            out["osc"] = "%s:%d" % self.udp.getsockname()[:2]
        return out

    def poll(self, timeout_ms: int) -> dict:
        try:
            return dict(self.poller.poll(timeout_ms))
        except zmq.ZMQError as e:
            if e.errno != errno.EINTR:
                raise
            return {}

    def receive(self, ready: dict) -> None:
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
                        self.on_reject(None, "bad_envelope", f"ROUTER message of {len(parts)} frame(s)", None, None)
                        continue
                    origin: Origin = ("router", parts[:-1])
                else:
                    origin = ("pull", None)
                self.on_message(parts[-1], origin, arrived)
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
                self.on_message(data, ("osc", addr), time.perf_counter())

    def send(self, origin: Origin, msg: wire.Message, publish: bool = False) -> None:
        """Answer on the origin's transport; ``publish`` also puts it on PUB (topic = stream).
        Answers to PULL/SUB input (acks, drops, errors) go to PUB, since there is no way back."""
        kind = origin[0]
        try:
            body: bytes | None = None
            if kind == "osc":
                assert self.udp is not None
                self.udp.sendto(osc.encode(msg), self.cfg.osc_send or origin[1])
            elif kind == "router" and self.router is not None:
                body = wire.encode(msg)
                self.router.send_multipart([*origin[1], body], zmq.NOBLOCK)
            elif kind == "pull" and self.pub is not None and not publish:
                topic = getattr(msg, "stream", None) or ""
                self.pub.send_multipart([topic.encode(), wire.encode(msg)], zmq.NOBLOCK)
            if publish and self.pub is not None:
                self.pub.send_multipart([msg.stream.encode(), body or wire.encode(msg)], zmq.NOBLOCK)  # type: ignore[union-attr]
        except zmq.Again:
            self.metrics.inc("send_dropped")  # peer over its high-water mark: drop, never block
        except (OSError, zmq.ZMQError) as e:
            self.metrics.inc("send_errors")  # e.g. EHOSTUNREACH: the peer disconnected
            self.log("debug", "send_error", transport=kind, error=str(e))

    def close(self, linger_ms: int = 0) -> None:
        for s in (self.router, self.pull, self.sub, self.pub):
            if s is not None:
                s.setsockopt(zmq.LINGER, linger_ms)
                s.close()
        self.router = self.pull = self.sub = self.pub = None
        if self.udp is not None:
            self.udp.close()
            self.udp = None
        if self.ctx is not None:
            self.ctx.term()
            self.ctx = None


def _bind(s: zmq.Socket, endpoint: str, key: str) -> None:
    try:
        s.bind(endpoint)
    except zmq.ZMQError as e:
        raise OSError(f"{key} {endpoint}: cannot bind ({e})") from None
