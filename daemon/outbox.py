"""Encode -> transport: the answers of a turn leave the daemon's sockets (the out side of
:class:`daemon.transport.Transports`, which it is mixed into).

``send(origin, message, publish)`` answers on the transport the message came from and, for filled
frames, also publishes on PUB.  Between ``hold()`` and ``flush()`` ZeroMQ answers are queued and then
sent together; answers to the frames of a ``frames`` bundle (origin ``("router", envelope, "bundle")``)
are joined, per peer, into one ``replies`` message at the flush.  Sends never block: a peer over its
high-water mark loses that answer and the loss is counted.
"""
from __future__ import annotations

import socket
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import msgpack
import zmq

from daemon import osc, oscblock, wire

if TYPE_CHECKING:
    from daemon.config import Config
    from daemon.metrics import Metrics

Origin = tuple[Any, ...]  # daemon.session.Origin: (transport name, address[, "bundle"])
Socket = zmq.Socket[Any]
_NOBLOCK = int(zmq.NOBLOCK)
_MORE_NOBLOCK = int(zmq.SNDMORE | zmq.NOBLOCK)
FLUSH_MAX = 64  # held answers sent at once, at most (fewer when the hwm is small)


class Outbox:
    """The sending half of :class:`daemon.transport.Transports`: its sockets are the transport's."""

    if TYPE_CHECKING:  # (set up by Transports)
        cfg: Config
        metrics: Metrics
        log: Callable[..., None]
        router: Socket | None
        pub: Socket | None
        udp: socket.socket | None

    def __init__(self, cfg: Config) -> None:
        self._held: list[tuple[Socket, list[bytes], str]] | None = None
        # ROUTER envelope -> held answers to bundled frames, as maps: packed in one pass at the flush
        self._bundles: dict[tuple[bytes, ...], list[dict[str, Any]]] = {}
        self._pack = msgpack.Packer(use_bin_type=True).pack  # one for the daemon's thread (packb builds one per call)
        self._flush_every = max(1, min(FLUSH_MAX, cfg.zmq_hwm // 4))

    def hold(self) -> None:
        """Queue ZeroMQ answers until :meth:`flush` (the daemon holds them for one loop turn):
        the sends then run back to back after the tick's work, instead of waking ZeroMQ's I/O
        thread between every two fills while the rest of the tick is still being computed."""
        if self._held is None:
            self._held = []

    def send_held(self) -> int:
        """Send what :meth:`hold` queued so far and go on holding (a turn's fills go out before
        its drops); outside a held turn, nothing to do.  Returns the answers sent."""
        if self._held is None:
            return 0
        n = self.flush()
        self._held = []
        return n

    def flush(self) -> int:
        """Send what is held and stop holding; returns the answers sent (a `replies` counts its answers)."""
        held, self._held = self._held, None
        n = 0
        if held:
            for sock_, parts, kind in held:
                self._zsend(sock_, parts, kind)
            n = len(held)
        if self._bundles:
            bundles, self._bundles = self._bundles, {}
            pack = self._pack
            for envelope, maps in bundles.items():
                for i in range(0, len(maps), wire.MAX_BUNDLE):
                    chunk = maps[i:i + wire.MAX_BUNDLE]
                    # one msgpack pass over the chunk's answers: the bytes join_replies would give
                    self._zsend(self.router, [*envelope, wire.replies_of(chunk, pack)], "router")  # type: ignore[arg-type]
                    n += len(chunk)  # (answers, for what an answer costs to send)
        return n

    def _zsend(self, sock_: Socket, parts: list[bytes], kind: str) -> None:
        try:
            # send_multipart, without its per-part checks and enum flag arithmetic (hot path)
            send = sock_.send
            for part in parts[:-1]:
                send(part, _MORE_NOBLOCK)
            send(parts[-1], _NOBLOCK)
        except zmq.Again:
            self.metrics.inc("send_dropped")  # peer over its high-water mark: drop, never block
        except (OSError, zmq.ZMQError) as e:
            self.metrics.inc("send_errors")  # e.g. EHOSTUNREACH: the peer disconnected
            self.log("debug", "send_error", transport=kind, error=str(e))

    def _zmq(self, sock_: Socket, parts: list[bytes], kind: str) -> None:
        held = self._held
        if held is None:
            self._zsend(sock_, parts, kind)
            return
        held.append((sock_, parts, kind))
        if len(held) >= self._flush_every:
            # a burst to one peer beyond about half its high-water mark can find the pipe full
            # (libzmq's writer sees free space in steps of hwm/2) and would lose answers
            self.flush()
            self.hold()

    def _encode(self, msg: wire.Message) -> bytes:
        """``wire.encode``, with this thread's Packer."""
        return self._pack(wire.fill_map(msg) if type(msg) is wire.FillMsg else wire.to_map(msg))  # type: ignore[no-any-return]

    def send(self, origin: Origin, msg: wire.Message, publish: bool = False) -> None:
        """Answer on the origin's transport; ``publish`` also puts it on PUB (topic = stream).
        Answers to PULL/SUB input (acks, drops, errors) go to PUB, since there is no way back."""
        kind = origin[0]
        if kind == "osc":
            assert self.udp is not None
            try:
                self.udp.sendto(osc.encode(msg), self.cfg.osc_send or origin[1])
            except OSError as e:
                self.metrics.inc("send_errors")
                self.log("debug", "send_error", transport=kind, error=str(e))
        body: bytes | None = None
        if kind == "router" and self.router is not None:
            if len(origin) == 2:
                body = self._encode(msg)
                self._zmq(self.router, [*origin[1], body], kind)
            else:  # an answer to a bundled frame: it goes back in one `replies`, packed at the flush
                m = wire.fill_map(msg) if type(msg) is wire.FillMsg else wire.to_map(msg)
                if self._held is not None:
                    self._bundles.setdefault(tuple(origin[1]), []).append(m)
                else:
                    self._zsend(self.router, [*origin[1], wire.replies_of([m], self._pack)], kind)
        elif kind == "pull" and self.pub is not None and not publish:
            topic = getattr(msg, "stream", None) or ""
            self._zmq(self.pub, [topic.encode(), self._encode(msg)], "pub")
        if publish and self.pub is not None:
            self._zmq(self.pub, [msg.stream.encode(), body or self._encode(msg)], "pub")  # type: ignore[union-attr]

    def send_fill_maps(self, origin: Origin, maps: list[dict[str, Any]]) -> None:
        """:meth:`send` with ``publish`` for each of a bundle's fills given as maps (daemon/tickblock.py), in order."""
        if origin[0] == "osc":  # (each fill's datagram, then PUB: daemon/oscblock.py)
            return oscblock.send_fills(self, origin, maps)
        pub, pack = self.pub, self._pack
        router, envelope = (self.router, tuple(origin[1])) if origin[0] == "router" else (None, ())
        for m in maps:
            if router is not None:
                if self._held is not None:  # (looked up each time: a flush for PUB's sake empties it)
                    self._bundles.setdefault(envelope, []).append(m)
                else:
                    self._zsend(router, [*origin[1], wire.replies_of([m], pack)], "router")
            if pub is not None:
                self._zmq(pub, [m["stream"].encode(), pack(m)], "pub")
