"""Transports: the daemon's sockets (ZeroMQ ROUTER/PULL/SUB/PUB, OSC over UDP) behind one poller.

``receive(ready)`` drains what arrived (bounded per socket and tick) and hands the turn's messages
(ZeroMQ, then OSC datagrams), each socket's in arrival order, to ``on_batch([(bytes, origin, arrival time),
...])`` (by default ``on_message`` for each).  The answers go out through the same sockets: ``send``,
``hold`` and ``flush`` are daemon/outbox.py's.

``receive`` reads everything waiting (up to DRAIN_MAX a socket) before it handles any of it, so the sessions
see the newest frame of every stream and conflate the rest.  Reading less per turn does not shorten a frame's
wait, it moves part of it into the socket where nothing sees it or conflates it (tried and reverted;
docs/BENCHMARKS.md, the overload paragraph).
"""
from __future__ import annotations

import errno
import socket
import time
from collections.abc import Callable
from typing import Any

import zmq

from daemon import security
from daemon.config import Config
from daemon.metrics import Metrics
from daemon.outbox import Origin, Outbox, Socket

DRAIN_MAX = 2048  # messages read per socket per tick: keeps one busy socket from starving the rest
DRAIN_MAX_BYTES = 1 << 20  # and bytes: a turn of big requests (hellos of 4096 names) is cut short
UDP_MAX = 65535  # bytes
_NOBLOCK = int(zmq.NOBLOCK)
_EVENTS, _POLLIN = int(zmq.EVENTS), int(zmq.POLLIN)
ZMQ_MAXMSG_MARGIN = 64 << 10  # bytes a frame may exceed max_message_bytes and still be read (and answered too_large)
# the ROUTER's receive queue per peer, at most (full: the DEALER waits, nothing dropped); a starved
# daemon held zmq.hwm frames a stream in libzmq, all conflated when read (bench/notebook/immut.md)
RCVHWM_ROUTER = 100


class Transports(Outbox):
    def __init__(self, cfg: Config, on_message: Callable[[bytes, Origin, float], None],
                 on_reject: Callable[..., None], metrics: Metrics, log: Callable[..., None],
                 on_batch: Callable[[list[tuple[bytes, Origin, float]]], None] | None = None):
        self.cfg = cfg
        self.on_message = on_message
        self.on_batch = on_batch or self._each
        self.on_reject = on_reject
        self.metrics = metrics
        self.log = log
        self.ctx: zmq.Context[Any] | None = None
        self.router: Socket | None = None
        self.pull: Socket | None = None
        self.sub: Socket | None = None
        self.pub: Socket | None = None
        self.udp: socket.socket | None = None
        self.guard: security.Guard | None = None
        self.poller = zmq.Poller()
        super().__init__(cfg)  # the held answers (daemon/outbox.py)
        self._curve = False  # set in open() when the sockets are CURVE servers

    def _each(self, items: list[tuple[bytes, Origin, float]]) -> None:
        for it in items:
            self.on_message(*it)

    def _sock(self, kind: int) -> Socket:
        assert self.ctx is not None
        c = self.cfg
        s: Socket = self.ctx.socket(kind)
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.SNDHWM, c.zmq_hwm)
        s.setsockopt(zmq.RCVHWM, min(c.zmq_hwm, RCVHWM_ROUTER) if kind == zmq.ROUTER else c.zmq_hwm)
        # a frame beyond this makes ZeroMQ disconnect the peer without reading it into memory;
        # between max_message_bytes and this the daemon reads it and answers `too_large`.  It
        # is per frame: the frames of a message beyond its envelope are dropped uncopied
        # (_recv_bounded), so one message costs at most 3 frames of this size
        s.setsockopt(zmq.MAXMSGSIZE, c.max_message_bytes + ZMQ_MAXMSG_MARGIN)
        assert self.guard is not None
        (self.guard.client if kind == zmq.SUB else self.guard.server)(s)  # CURVE when keys are configured
        return s

    def open(self) -> None:
        """Bind/connect everything the config names.  Raises zmq.ZMQError/OSError naming the address."""
        c = self.cfg
        self.ctx = zmq.Context()
        try:
            self.guard = security.Guard(self.ctx, c.security)  # ZAP allow list of client keys, OSC sources
            self._curve = self.guard.spec.curve
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
                out[name] = bytes(s.getsockopt(zmq.LAST_ENDPOINT)).decode()
        if self.sub is not None:
            out["sub"] = self.cfg.zmq_sub
        if self.udp is not None:
            host, port = self.udp.getsockname()[:2]
            out["osc"] = f"{host}:{port}"
        return out

    def poll(self, timeout_ms: int) -> dict[Any, int]:
        try:
            return dict(self.poller.poll(timeout_ms))
        except zmq.ZMQError as e:
            if e.errno != errno.EINTR:
                raise
            return {}

    def receive(self, ready: dict[Any, int], arrived: float | None = None) -> None:
        """Read what ``ready`` (a poll's answer) says is waiting and hand it to ``on_batch``.  A
        message's receipt time is time.perf_counter() as it is read, or ``arrived`` for every one
        when given (the loop's: the start of a rehearsal they waited through, daemon/wait.py)."""
        batch: list[tuple[bytes, Origin, float]] = []
        for sock_, name in ((self.router, "router"), (self.pull, "pull"), (self.sub, "sub")):
            if sock_ is None or sock_ not in ready:
                continue
            # read everything waiting first, then handle it: the socket calls run back to back
            # (ZeroMQ's I/O thread is not woken between them) and the scheduler sees the whole burst
            got = []
            keep = _KEEP[name]
            keyed = self._curve and name == "router"
            nbytes = 0
            for i in range(DRAIN_MAX):
                # (after the first, which the poll said is there: read only while ZeroMQ says one
                # is waiting, so the drain does not end in a failing recv: cold, that recv and its
                # zmq.Again, built in Python, cost ~60 us a turn, the check ~30: floor-7.md)
                if i and not sock_.getsockopt(_EVENTS) & _POLLIN:  # type: ignore[operator]  # (an int for EVENTS)
                    break
                try:
                    parts = _recv_bounded(sock_, keep, keyed)
                except zmq.Again:
                    break
                got.append((parts, time.perf_counter() if arrived is None else arrived))
                nbytes += len(parts[-1]) if type(parts[-1]) is bytes else 0
                if nbytes > DRAIN_MAX_BYTES:  # (the rest next turn: one turn's decoding stays bounded)
                    break
            for parts, arrived in got:
                n = len(parts)
                if name == "router":
                    # [routing id, body] from a DEALER, [routing id, "", body] from a REQ: anything
                    # else is refused, and the answer goes to the routing id alone, so leading
                    # frames never become an envelope the daemon holds for a peer (the size cap
                    # covers the body; the envelope is bounded to 255 + 0 bytes)
                    if n == 2 or (n == 3 and not parts[1]):
                        origin: Origin = ("router", parts[:-1] if not keyed
                                          else _Keyed(parts[:-1], parts.key))  # type: ignore[attr-defined]
                    else:
                        n = n if type(parts[-1]) is not int else n - 1 + parts[-1]
                        self.on_reject(("router", parts[:1]), "bad_envelope",
                                       f"ROUTER message of {n} frame(s): send one "
                                       f"frame from a DEALER, or [\"\", body] from a REQ", None, None)
                        continue
                elif n == 1 or (n == 2 and name == "sub" and len(parts[0]) <= 256):  # (SUB: [topic, body])
                    origin = ("pull", None)
                else:
                    self.on_reject(None, "bad_envelope", f"{name.upper()} message of more than {keep} frame(s): "
                                   f"one frame per message", None, None)
                    continue
                batch.append((parts[-1], origin, arrived))
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
                if self.guard is not None and not self.guard.osc_allowed(addr):
                    self.metrics.reject("source_not_allowed")  # counted, never answered (no reflection)
                    continue
                batch.append((data, ("osc", addr), time.perf_counter() if arrived is None else arrived))
        if batch:
            self.on_batch(batch)

    def operator(self, origin: Origin) -> bool:
        """May this peer act on others' streams and reload?  Without CURVE every ROUTER peer is
        local (non-loopback binds need CURVE) and is one; with CURVE, a key listed in
        security.operator_keys.  OSC and PULL/SUB peers never are."""
        if origin[0] != "router":
            return False
        if not self._curve:
            return True
        key = getattr(origin[1], "key", None)
        return key is not None and self.guard is not None and self.guard.is_operator(key)

    def close(self, linger_ms: int = 0) -> None:
        for s in (self.router, self.pull, self.sub, self.pub):
            if s is not None:
                s.setsockopt(zmq.LINGER, linger_ms)
                s.close()
        self.router = self.pull = self.sub = self.pub = None
        if self.udp is not None:
            self.udp.close()
            self.udp = None
        if self.guard is not None:
            self.guard.close()  # its ZAP thread holds sockets of ctx: stop it before ctx.term()
            self.guard = None
        if self.ctx is not None:
            self.ctx.term()
            self.ctx = None


_KEEP = {"router": 3, "pull": 1, "sub": 2}  # frames of a message that can be valid: [id, "", body], [body], [topic, body]


class _Keyed(list[Any]):
    """A ROUTER envelope (sent back as its frames) that also carries the CURVE public key (Z85)
    its message was authenticated with: read from that very message, so a routing id reused by
    another connection can never inherit a key."""

    __slots__ = ("key",)

    def __init__(self, frames: list[Any], key: str | None):
        super().__init__(frames)
        self.key = key


def _recv_bounded(sock_: Socket, keep: int, keyed: bool = False) -> list[Any]:
    """One multipart message, at most ``keep`` frames of it copied into Python: the frames after
    those (the message is refused) are taken zero-copy and dropped at once, so a peer sending
    many leading frames costs neither a copy nor memory held (each frame is capped by
    MAXMSGSIZE, the number of them by nothing in ZeroMQ).  An over-long message comes back as
    its first ``keep`` frames and then the count of frames dropped (an int).  ``keyed`` (CURVE
    on a ROUTER): the result is a :class:`_Keyed` whose ``key`` is the message's ZAP User-Id,
    the peer's public key, so streams are owned by keys, not connections."""
    # each frame is taken as a zmq.Frame (copy=False) and read with .bytes: its ``more`` flag
    # comes with it, where recv() of bytes needs a getsockopt(RCVMORE) call per frame (about
    # half the cost of reading a message)
    recv = sock_.recv
    f = recv(_NOBLOCK, copy=False)
    if not keyed:
        parts: list[Any] = [f.bytes]
    else:
        try:
            got = f.get("User-Id")
            key = got if isinstance(got, str) else None
        except zmq.ZMQError:
            key = None
        parts = _Keyed([f.bytes], key)
    while f.more:
        f = recv(_NOBLOCK, copy=False)
        if len(parts) < keep:
            parts.append(f.bytes)
            continue
        dropped = 1  # the frames beyond ``keep``: taken and let go, never copied
        while f.more:
            f = recv(_NOBLOCK, copy=False)
            dropped += 1
        parts.append(dropped)
        break
    return parts


def _bind(s: Socket, endpoint: str, key: str) -> None:
    try:
        s.bind(endpoint)
    except zmq.ZMQError as e:
        raise OSError(f"{key} {endpoint}: cannot bind ({e})") from None
