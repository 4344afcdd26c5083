"""The view served by the daemon itself, at ``/view/`` of its metrics HTTP endpoint.

``[metrics] view = true`` (off by default; needs ``metrics.http`` and ``zmq.pub``).  Nothing here
runs on the daemon's serving loop: the metrics HTTP thread (``daemon/metrics_http.py``, one
selector, non-blocking sockets) calls :meth:`DaemonView.tick` at the display rate.  A tick reads
what the daemon published on its own PUB socket since the last one through a SUB of its own
(ZeroMQ drops what a slow subscriber does not take: the daemon never waits for it), keeps only
the newest message of each stream (the topic), decodes those few, and turns them into one page
update with :class:`view.feed.Feed` (one batched FK call for all streams).  The serving loop's
cost is the PUB send it already does; the view's is about N decodes and one FK call per tick,
and nothing at all while no page is open (the SUB subscribes only while one is).

Per-frame latency figures are sampled at the display rate (the newest fill of each tick), not
taken from every fill as the standalone ``lacuna view`` does.
"""
from __future__ import annotations

import time
from typing import Any

import zmq

from daemon import wire
from view.feed import Feed, Skeleton, dumps

RATE_HZ = 30.0
MAX_DRAIN = 20000  # PUB messages read per tick at most (the rest wait, or ZeroMQ drops them)
RCVHWM = 4096
KEEPALIVE_S = 5.0


def local_endpoint(pub: str) -> str:
    """Where a SUB in the daemon reaches its own PUB (a wildcard bind -> loopback)."""
    return pub.replace("://*:", "://127.0.0.1:").replace("://0.0.0.0:", "://127.0.0.1:").replace("://[::]:", "://[::1]:")


class DaemonView:
    """SUB on the daemon's PUB -> one SSE chunk per display frame (see the module docstring)."""

    def __init__(self, pub_endpoint: str, skeleton: Skeleton | None, channels: list[str] | None,
                 source: str = "", rate: float = RATE_HZ):
        self.feed = Feed(skeleton, channels, rate=rate, mode="live", source=source)
        self.period = 1.0 / rate
        self.next_t = time.monotonic()
        self.ctx = zmq.Context()
        self.sub = self.ctx.socket(zmq.SUB)
        self.sub.setsockopt(zmq.LINGER, 0)
        self.sub.setsockopt(zmq.RCVHWM, RCVHWM)
        self.sub.connect(local_endpoint(pub_endpoint))
        self.watched = False  # subscribed only while a page is open: with none, PUB sends it nothing
        self.meta_sent = -1
        self.meta_chunk = b""
        self.read = self.decoded = self.undecodable = self.ticks = 0
        self.last_sent = time.monotonic()

    def watch(self, pages: int) -> None:
        """``pages`` feeds are open: subscribe at the first, unsubscribe after the last."""
        if (pages > 0) != self.watched:
            self.watched = pages > 0
            self.sub.setsockopt(zmq.SUBSCRIBE if self.watched else zmq.UNSUBSCRIBE, b"")

    def due_in(self, now: float) -> float:
        return max(0.0, self.next_t - now)

    def hello_chunk(self) -> bytes:
        """What a page connecting now gets first: the newest meta."""
        if not self.meta_chunk:
            self._meta()
        return self.meta_chunk

    def _meta(self) -> bool:
        m = self.feed.meta()
        changed = m["version"] != self.meta_sent
        self.meta_sent = m["version"]
        self.meta_chunk = f"event: meta\ndata: {dumps(m)}\n\n".encode()
        return changed

    def tick(self, now: float) -> bytes | None:
        """The SSE bytes for every open page this display frame (None: nothing to send)."""
        self.next_t = max(self.next_t + self.period, now)  # (a stalled machine does not catch up)
        self.ticks += 1
        newest: dict[bytes, bytes] = {}
        for _ in range(MAX_DRAIN):
            try:
                parts = self.sub.recv_multipart(zmq.NOBLOCK, copy=True)
            except zmq.Again:
                break
            self.read += 1
            if len(parts) == 2:
                newest[parts[0]] = parts[1]
        for body in newest.values():
            try:
                msg = wire.decode(body, wire.MAX_MESSAGE_BYTES)
            except wire.WireError:
                self.undecodable += 1
                continue
            self.decoded += 1
            if isinstance(msg, wire.FillMsg):
                self.feed.on_fill(msg)
            elif isinstance(msg, wire.HelloAck):
                self.feed.on_ack(msg)
        try:
            upd = self.feed.tick()
        except Exception as e:  # noqa: BLE001 - the page says what broke; the daemon serves on
            self.feed.fail(f"view: {type(e).__name__}: {e}"[:300])
            upd = None
        out = b""
        if self.feed.meta_version != self.meta_sent and self._meta():
            out += self.meta_chunk
        if upd is not None:
            out += f"event: frame\ndata: {dumps(upd)}\n\n".encode()
        if not out and now - self.last_sent >= KEEPALIVE_S:
            out = b": keepalive\n\n"
        if out:
            self.last_sent = now
        return out or None

    def info(self) -> dict[str, Any]:
        return {"ticks": self.ticks, "read": self.read, "decoded": self.decoded, "undecodable": self.undecodable,
                "streams": len(self.feed.streams)}

    def close(self) -> None:
        self.sub.close(0)
        self.ctx.term()


def from_config(cfg: Any, models: dict[str, Any]) -> DaemonView | None:
    """The daemon's view when ``[metrics] view`` is on (None otherwise): drawn on the default
    model's training skeleton (``daemon.positions``), its channels the streams' default names."""
    if not getattr(cfg, "metrics_view", False):
        return None
    from daemon import positions

    name = cfg.default_model
    loaded = models.get(name) if name else None
    skel, channels, source = None, None, "this daemon's PUB"
    if loaded is not None:
        channels = list(loaded.model.channels or []) or None
        try:
            skel = Skeleton(positions.kinematics(loaded.model, name), None, f"model {name}'s training skeleton")
        except ValueError:
            skel = None  # the page says "no skeleton" for each stream
    return DaemonView(cfg.zmq_pub, skel, channels, source)
