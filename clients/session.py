"""The client side of one stream, without sockets: what the blocking and asyncio clients share.

A :class:`StreamSession` holds everything about a stream that survives a reconnect: the stream
id, the studio's channel names and model (the handshake), and the next sequence number.  What a
daemon restart loses (the daemon's filter state for the stream) cannot be kept by a client; the
session re-sends the handshake so the new daemon maps the channels the same way, and the
sequence numbers go on from where they were, so downstream tools never see them jump back.

It also watches the socket's monitor events: a TCP disconnect means the daemon may have been
restarted and forgotten the handshake, so the next frame is preceded by a fresh ``hello``.
"""
from __future__ import annotations

import secrets
import time
from typing import Any

import numpy as np
import zmq
from zmq.utils.monitor import parse_monitor_message

from daemon import wire
from lacuna.errors import LacunaError

# Timeouts and retries (module constants, units in the names).
DEFAULT_TIMEOUT_S = 1.0  # how long one request waits for its answer before the link is rebuilt
DEFAULT_RETRIES = 3  # rebuilds of the link per request before DaemonUnavailable
RECONNECT_IVL_MS = 50  # ZeroMQ's own TCP reconnect interval, first try
RECONNECT_IVL_MAX_MS = 1000  # ... capped exponential backoff
MONITOR_EVENTS = zmq.EVENT_DISCONNECTED | zmq.EVENT_HANDSHAKE_SUCCEEDED

# Error codes after which re-sending the handshake can help (the daemon lost the stream's mapping).
REHELLO_REASONS = ("width",)


class DaemonUnavailable(LacunaError):
    """No answer from the daemon within the timeout, after every retry."""


class DaemonRefused(LacunaError):
    """The daemon answered with an ``error`` message (reason and detail in the text)."""

    def __init__(self, err: wire.ErrorMsg):
        self.error = err
        super().__init__(f"daemon refused the message: {err.reason}: {err.detail}")


def dealer_socket(ctx: zmq.Context[Any], endpoint: str, timeout_s: float,
                  curve: tuple[str, str] | None = None) -> zmq.Socket[Any]:
    """A DEALER connected to ``endpoint`` with the options every client uses; ``curve`` =
    (this client's .key_secret file, the daemon's public .key file) for a daemon with keys."""
    s = ctx.socket(zmq.DEALER)
    if curve is not None:
        from daemon.security import configure_client

        configure_client(s, *curve)
    s.setsockopt(zmq.LINGER, 0)  # never block close on unsent frames of a dead daemon
    # IMMEDIATE: queue nothing while no daemon is connected, so stale frames are never
    # delivered to a daemon that comes back later; send blocks up to SNDTIMEO instead.
    s.setsockopt(zmq.IMMEDIATE, 1)
    s.setsockopt(zmq.SNDTIMEO, max(1, int(timeout_s * 1000)))
    s.setsockopt(zmq.RECONNECT_IVL, RECONNECT_IVL_MS)
    s.setsockopt(zmq.RECONNECT_IVL_MAX, RECONNECT_IVL_MAX_MS)
    s.connect(endpoint)
    return s  # type: ignore[no-any-return]


class StreamSession:
    """Per-stream client state that survives reconnects.

    Parameters
    ----------
    stream : stream id (1..128 printable characters).
    channels : the studio's channel names in frame order, or None to use the model's own list
        (then no handshake is sent and frames must have the model's width).
    model : model name from the daemon's config, or None for the daemon's choice.
    positions : ask (in the hello) for joint positions in every fill (``FillMsg.positions``, (J, 3)
        metres); the hello's answer names the joints (``ack.joints``, ``ack.parents``).
    """

    def __init__(self, stream: str, channels: list[str] | None = None, model: str | None = None, first_seq: int = 0,
                 positions: bool = False):
        if not stream or len(stream) > wire.MAX_STREAM_ID or not stream.isprintable():
            raise ValueError(f"stream id must be 1..{wire.MAX_STREAM_ID} printable characters (got {stream!r})")
        if positions and channels is None:
            raise ValueError("positions are asked for in the hello: pass the stream's channel list")
        self.positions = bool(positions)
        self.stream = stream
        self.channels = list(channels) if channels is not None else None
        self.model = model
        self.next_seq = self.first_seq = int(first_seq)
        self.handshaken = channels is None  # nothing to tell the daemon
        self.ack: wire.HelloAck | None = None
        self.disconnects = 0
        self.reconnects = 0
        self.resyncs = 0  # times the daemon's view of the stream was put right (a `late` or `not_owner` we did not cause)
        # kept across reconnects: a hello that carries it takes the stream back from the old connection
        self.claim = secrets.token_hex(16)

    @property
    def n_channels(self) -> int | None:
        return None if self.channels is None else len(self.channels)

    # ---- messages --------------------------------------------------------------------------
    def hello_bytes(self) -> bytes:
        assert self.channels is not None
        return wire.encode(wire.Hello(self.stream, self.channels, self.model, self.claim, self.positions))

    def frame_bytes(self, angles: Any, observed: Any = None, t: float | None = None,
                    seq: int | None = None) -> tuple[int, bytes]:
        """Encode one frame; takes the next sequence number unless ``seq`` is given.

        angles : (C,) degrees, NaN where missing.  observed : (C,) bool or None.
        """
        seq, msg = self.frame_msg(angles, observed, t, seq)
        return seq, wire.encode(msg)

    def frame_msg(self, angles: Any, observed: Any = None, t: float | None = None,
                  seq: int | None = None) -> tuple[int, wire.Frame]:
        """:meth:`frame_bytes` before encoding (a bundle encodes several at once)."""
        a = np.asarray(angles, dtype=np.float64)
        if a.ndim != 1:
            raise ValueError(f"angles must be one frame of shape (C,) (got shape {a.shape})")
        if self.channels is not None and a.shape[0] != len(self.channels):
            raise ValueError(f"stream {self.stream!r} has {len(self.channels)} channels; frame has {a.shape[0]}")
        obs = None
        if observed is not None:
            obs = np.asarray(observed, dtype=bool)
            if obs.shape != a.shape:
                raise ValueError(f"observed mask must have shape {a.shape} (got {obs.shape})")
            a = np.where(obs, a, np.nan)  # a masked-out slot may hold anything; NaN is unambiguous
        if seq is None:
            seq = self.next_seq
            self.next_seq += 1
        else:
            self.next_seq = max(self.next_seq, seq + 1)
        return seq, wire.Frame(self.stream, int(seq), float(time.time() if t is None else t), a.astype(np.float32), obs)

    def on_ack(self, msg: wire.Message) -> wire.HelloAck:
        if isinstance(msg, wire.ErrorMsg):
            raise DaemonRefused(msg)
        if not isinstance(msg, wire.HelloAck) or msg.stream != self.stream:
            raise DaemonRefused(wire.ErrorMsg("unexpected", f"expected hello-ack for {self.stream!r}, got {msg!r:.120}"))
        self.ack = msg
        self.handshaken = True
        return msg

    # ---- link watching ----------------------------------------------------------------------
    def link_lost(self) -> None:
        """The daemon may have restarted: send the handshake again before the next frame."""
        self.disconnects += 1
        if self.channels is not None:
            self.handshaken = False

    def drain_monitor(self, mon: zmq.Socket[Any] | None) -> None:
        """Read pending monitor events without blocking (a sync PAIR socket)."""
        if mon is None:
            return
        while True:
            try:
                parts = mon.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            except zmq.ZMQError:
                return
            ev = parse_monitor_message(parts)
            if ev["event"] == zmq.EVENT_DISCONNECTED:
                self.link_lost()


def open_monitor(sync_ctx: zmq.Context[Any], sock: zmq.Socket[Any], name: str) -> zmq.Socket[Any]:
    """Attach a monitor to ``sock`` and return the sync PAIR socket that reads its events."""
    addr = f"inproc://lacuna-monitor-{name}-{id(sock):x}"
    sock.monitor(addr, MONITOR_EVENTS)
    mon = sync_ctx.socket(zmq.PAIR)
    mon.setsockopt(zmq.LINGER, 0)
    mon.connect(addr)
    return mon  # type: ignore[no-any-return]
