"""Blocking client for pipeline code: one stream to ``lacuna serve`` over ZeroMQ request/reply.

    from clients import Client
    with Client("tcp://127.0.0.1:5555", "actor1", channels=studio_names) as c:
        fill = c.fill(angles, observed)        # wire.FillMsg: .angles, .filled, .std, .status
        c.send(angles); reply = c.recv()       # or pipelined

It uses a DEALER socket (the daemon's side is a ROUTER), so it may pipeline frames and match the
answers by ``seq``.  A request that gets no answer within ``timeout_s`` rebuilds the socket
(Lazy Pirate, zguide ch. 4) and retries; a TCP disconnect seen on the socket monitor makes the
next frame re-send the handshake first, so a daemon restarted under the client maps the studio's
channels the same way.  Stream id, handshake and sequence numbers survive; the daemon's filter
state for the stream does not (it lived in the old process).  The handshake carries a claim
token kept across reconnects, so the new connection takes its stream back from the old one
(streams are owned, docs/PROTOCOL.md); a ``late`` answer to a frame newer than any sent (the
daemon's sequence is ahead of ours) or a ``not_owner`` makes the client restart its stream
once (a fresh hello, or a reset) and send the frame again.
"""
from __future__ import annotations

import time
from typing import Any

import zmq

from clients.control import control, decode_reply
from clients.session import (
    DEFAULT_RETRIES,
    DEFAULT_TIMEOUT_S,
    REHELLO_REASONS,
    DaemonRefused,
    DaemonUnavailable,
    StreamSession,
    dealer_socket,
    open_monitor,
)
from daemon import wire

RELEASE_WAIT_S = 0.5  # Client.close waits at most this for the daemon to confirm its streams are released


class _DealerLink:
    """Socket lifecycle shared by the blocking and the asyncio client: subclasses set ``sock``,
    ``_mon``, ``ctx``, ``_own_ctx``, ``session`` and implement ``_open``."""

    session: StreamSession

    sock: Any
    _mon: Any
    _monitor_name = ""

    def _link(self, endpoint: str, timeout_s: float, retries: int, ctx: zmq.Context[Any] | None) -> None:
        """The blocking clients' connection state; the socket opens in ``_open``."""
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be positive (got {timeout_s})")
        self.endpoint = endpoint
        self.timeout_s, self.retries = float(timeout_s), int(retries)
        self._own_ctx = ctx is None
        self.ctx = ctx or zmq.Context()
        self.sock = None
        self._mon = None

    curve: tuple[str, str] | None = None

    def _open(self) -> None:
        self.sock = dealer_socket(self.ctx, self.endpoint, self.timeout_s, self.curve)
        self._mon = open_monitor(self.ctx, self.sock, self._monitor_name)

    def _close_socket(self) -> None:
        if self.sock is not None:
            try:
                self.sock.disable_monitor()
            except zmq.ZMQError:
                pass
            self.sock.close(linger=0)
            self.sock = None
        if self._mon is not None:
            self._mon.close(linger=0)
            self._mon = None

    def reconnect(self) -> None:
        """Throw the socket away and open a fresh one; the handshake is re-sent before the next frame."""
        self._close_socket()
        self.session.reconnects += 1
        self.session.link_lost()
        self._open()

    def _release(self, streams: list[str]) -> None:
        """Give our streams up before the socket goes (``release``; docs/PROTOCOL.md, stream
        ownership): the next client to open them, a restarted plugin say, owns them at once
        instead of after idle_timeout_s.  Best effort, a short wait: a daemon that does not
        answer (gone, or older than ownership) changes nothing."""
        if self.sock is None:
            return
        try:
            for sid in streams:
                self.sock.send(wire.encode(wire.Control("release", sid)), zmq.NOBLOCK)
            deadline = time.monotonic() + min(self.timeout_s, RELEASE_WAIT_S)
            left = len(streams)
            while left and self.sock.poll(max(0, int((deadline - time.monotonic()) * 1000)), zmq.POLLIN):
                m = decode_reply(self.sock.recv())
                if (isinstance(m, wire.ControlReply) and m.cmd == "release") or \
                        (isinstance(m, wire.ErrorMsg) and m.seq is None):
                    left -= 1
        except (zmq.ZMQError, ValueError, wire.WireError):
            pass

    def close(self) -> None:
        """Release our streams, close the socket and, if the context is ours, end it.  The context
        is ended with ``destroy(linger=0)``, which closes any socket of it still open first: a
        Ctrl-C that lands inside ``_open`` (the socket made, not yet kept in ``self.sock``) leaves
        one behind that only its traceback holds, and ``term()`` would wait for it forever."""
        try:
            self._release(self._owned_streams())
        finally:
            self._close_socket()
            if self._own_ctx:
                self.ctx.destroy(linger=0)

    def _owned_streams(self) -> list[str]:
        return []


class Client(_DealerLink):
    """One stream's connection to the daemon.

    Parameters
    ----------
    endpoint : the daemon's ROUTER, e.g. ``tcp://127.0.0.1:5555``.
    stream : stream id.
    channels : studio channel names (frame order); None = the model's own list, no handshake.
    model : model name in the daemon's config, or None for its default.
    timeout_s : how long one request waits for its answer.
    retries : how many times a request is re-sent on a fresh socket before DaemonUnavailable.
    curve : (this client's .key_secret file, the daemon's public .key file) for a daemon with keys.
    claim : the stream's claim token, to keep across client restarts (default: a fresh random one).
    positions : every fill also carries ``.positions``, (J, 3) float32 joint positions in metres
        (the model's training skeleton); ``joints``/``parents`` name them after the handshake.
    """

    def __init__(self, endpoint: str, stream: str, channels: list[str] | None = None, model: str | None = None,
                 *, timeout_s: float = DEFAULT_TIMEOUT_S, retries: int = DEFAULT_RETRIES,
                 ctx: zmq.Context[Any] | None = None, first_seq: int = 0, curve: tuple[str, str] | None = None,
                 claim: str | None = None, positions: bool = False):
        self.session = StreamSession(stream, channels, model, first_seq, positions)
        if claim is not None:
            self.session.claim = claim
        self.curve = curve
        self._link(endpoint, timeout_s, retries, ctx)
        self._monitor_name = self.session.stream.encode().hex()[:32]
        self._open()

    # ---- socket lifecycle ------------------------------------------------------------------
    def _owned_streams(self) -> list[str]:
        ss = self.session
        return [ss.stream] if ss.ack is not None or ss.next_seq > ss.first_seq else []

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ---- raw send / receive ----------------------------------------------------------------
    def _send(self, data: bytes) -> None:
        assert self.sock is not None
        try:
            self.sock.send(data, copy=False)
        except zmq.Again:
            raise TimeoutError("no daemon connected") from None

    def recv(self, timeout_s: float | None = None) -> wire.Message | None:
        """The next message from the daemon, or None after ``timeout_s`` (default: the client's)."""
        assert self.sock is not None
        t = self.timeout_s if timeout_s is None else timeout_s
        if not self.sock.poll(int(t * 1000), zmq.POLLIN):
            return None
        return decode_reply(self.sock.recv())

    def _ensure_handshake(self) -> None:
        self.session.drain_monitor(self._mon)
        if not self.session.handshaken:
            self.hello()

    def hello(self) -> wire.HelloAck:
        """Send the handshake and wait for its ``hello-ack`` (retrying on a fresh socket)."""
        if self.session.channels is None:
            raise ValueError("this client has no channel list to hand over (channels=None)")
        for attempt in range(self.retries + 1):
            try:
                self._send(self.session.hello_bytes())
                deadline = time.monotonic() + self.timeout_s
                while True:
                    msg = self.recv(max(0.0, deadline - time.monotonic()))
                    if msg is None:
                        raise TimeoutError("no hello-ack")
                    if isinstance(msg, (wire.HelloAck, wire.ErrorMsg)):
                        return self.session.on_ack(msg)
                    # answers to frames pipelined before the handshake: not ours to keep here
            except TimeoutError:
                if attempt == self.retries:
                    break
                self.reconnect()
        raise DaemonUnavailable(f"no answer from {self.endpoint} to the handshake of {self.session.stream!r} "
                                f"after {self.retries + 1} tries of {self.timeout_s:g} s")

    @property
    def joints(self) -> list[str] | None:
        """With ``positions=True``: the joints of ``fill(...).positions``, in row order (after the
        handshake, which the first frame makes if ``hello()`` was not called)."""
        ack = self.session.ack
        return None if ack is None else ack.joints

    @property
    def parents(self) -> list[int] | None:
        """Parent index per joint (-1 for a root), as ``joints``."""
        ack = self.session.ack
        return None if ack is None else ack.parents

    def send(self, angles: Any, observed: Any = None, t: float | None = None, seq: int | None = None) -> int:
        """Send one frame without waiting; returns its sequence number.  Read answers with recv()."""
        self._ensure_handshake()
        seq, data = self.session.frame_bytes(angles, observed, t, seq)
        self._send(data)
        return seq

    def fill(self, angles: Any, observed: Any = None, t: float | None = None,
             seq: int | None = None) -> wire.FillMsg | wire.Drop:
        """Send one frame and wait for its answer: a FillMsg, or a Drop naming why it was not served.

        angles : (C,) degrees, NaN where missing; observed : (C,) bool or None.
        Raises DaemonUnavailable after every retry timed out, DaemonRefused on an ``error`` reply.
        """
        seq, data = self.session.frame_bytes(angles, observed, t, seq)
        resynced = False
        for attempt in range(self.retries + 1):
            try:
                self._ensure_handshake()
                self._send(data)
                msg = self._await_seq(seq)
            except TimeoutError:
                if attempt == self.retries:
                    break
                self.reconnect()
                continue
            if isinstance(msg, wire.ErrorMsg):
                if msg.reason in REHELLO_REASONS and self.session.channels is not None and attempt < self.retries:
                    self.session.handshaken = False  # the daemon lost our mapping: say it again
                    continue
                if msg.reason == "not_owner" and not resynced and attempt < self.retries:
                    resynced = self._resync_or_reconnect()  # our connection changed under a frame-only stream
                    continue
                raise DaemonRefused(msg)
            if isinstance(msg, wire.Drop) and msg.reason == "late" and not resynced and attempt < self.retries:
                # we never sent a later frame: the daemon's sequence for the stream is ahead of ours
                # for a reason we cannot see (another process of ours with the same key, an old
                # incarnation's frames): restart the stream once and send the frame again
                resynced = self._resync_or_reconnect()
                continue
            assert isinstance(msg, (wire.FillMsg, wire.Drop))  # (_await_seq returns nothing else)
            return msg
        raise DaemonUnavailable(f"no answer from {self.endpoint} for frame {seq} of {self.session.stream!r} "
                                f"after {self.retries + 1} tries of {self.timeout_s:g} s")

    def _resync_or_reconnect(self) -> bool:
        try:
            return self._resync()
        except TimeoutError:
            self.reconnect()
            return True

    def _resync(self) -> bool:
        """Restart the stream on the daemon from this connection: a fresh ``hello`` when there is
        a channel list (it restarts the stream and, with our claim token, takes it over),
        else a ``reset`` on this socket (the owner's, or an operator's).  Returns True."""
        self.session.resyncs += 1
        if self.session.channels is not None:
            self.session.handshaken = False
            return True
        assert self.sock is not None
        self._send(wire.encode(wire.Control("reset", self.session.stream)))
        deadline = time.monotonic() + self.timeout_s
        while True:
            msg = self.recv(max(0.0, deadline - time.monotonic()))
            if msg is None:
                raise TimeoutError("no answer to reset")
            if isinstance(msg, wire.ControlReply) and msg.cmd == "reset":
                return True
            if isinstance(msg, wire.ErrorMsg) and msg.seq is None:
                raise DaemonRefused(msg)

    def _await_seq(self, seq: int) -> wire.Message:
        deadline = time.monotonic() + self.timeout_s
        while True:
            msg = self.recv(max(0.0, deadline - time.monotonic()))
            if msg is None:
                raise TimeoutError(f"frame {seq}")
            if isinstance(msg, (wire.FillMsg, wire.Drop)) and msg.seq == seq:
                return msg
            if isinstance(msg, wire.ErrorMsg) and msg.seq in (seq, None):
                return msg
            # an answer to an earlier pipelined frame or a stale handshake: skip it

    # ---- control ---------------------------------------------------------------------------
    def control(self, cmd: str, stream: str | None = None) -> wire.ControlReply:
        """A control request (status, reset, reload, list-models) on this client's socket."""
        return control(self.endpoint, cmd, stream, timeout_s=self.timeout_s, ctx=self.ctx, curve=self.curve)

    def status(self) -> dict[str, Any]:
        r = self.control("status")
        if not r.ok:
            raise DaemonRefused(wire.ErrorMsg("status", r.error or "status failed"))
        return r.result


class CaptureClient(_DealerLink):
    """Several performers' streams of one capture system on one connection: each capture instant
    goes out as one ``frames`` bundle and its answers come back as one ``replies`` (docs/PROTOCOL.md).

        with CaptureClient("tcp://127.0.0.1:5555", {"actor1": names, "actor2": names}) as cap:
            out = cap.fill({"actor1": angles1, "actor2": (angles2, observed2)})
            out["actor1"].angles, out["actor2"].status       # FillMsg, or Drop / ErrorMsg for that stream

    Parameters as :class:`Client`, with ``streams`` mapping stream id -> studio channel names (or
    None for the model's own list).  A timeout rebuilds the socket, re-sends the handshakes and
    sends the bundle again (same sequence numbers), ``retries`` times, then DaemonUnavailable.
    """

    def __init__(self, endpoint: str, streams: dict[str, list[str] | None], model: str | None = None, *,
                 timeout_s: float = DEFAULT_TIMEOUT_S, retries: int = DEFAULT_RETRIES,
                 ctx: zmq.Context[Any] | None = None):
        if not streams:
            raise ValueError("a capture client needs at least one stream")
        if len(streams) > wire.MAX_BUNDLE:
            raise ValueError(f"at most {wire.MAX_BUNDLE} streams go in one bundle (got {len(streams)})")
        self.sessions = {sid: StreamSession(sid, ch, model) for sid, ch in streams.items()}
        self.session = next(iter(self.sessions.values()))  # _DealerLink counts reconnects on this one
        self._link(endpoint, timeout_s, retries, ctx)
        self._monitor_name = "capture-" + self.session.stream.encode().hex()[:24]
        self._open()

    def _owned_streams(self) -> list[str]:
        return [sid for sid, ss in self.sessions.items() if ss.ack is not None or ss.next_seq > ss.first_seq]

    def reconnect(self) -> None:
        super().reconnect()   # marks the first session
        for ss in list(self.sessions.values())[1:]:
            ss.link_lost()

    def __enter__(self) -> CaptureClient:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _recv(self, deadline: float) -> wire.Message:
        assert self.sock is not None
        if not self.sock.poll(max(0, int((deadline - time.monotonic()) * 1000)), zmq.POLLIN):
            raise TimeoutError
        return decode_reply(self.sock.recv())

    def _handshakes(self) -> None:
        seen = self.session.disconnects
        self.session.drain_monitor(self._mon)   # the monitor counts on the first session: pass it on
        if self.session.disconnects != seen:
            for ss in list(self.sessions.values())[1:]:
                ss.link_lost()
        todo = [ss for ss in self.sessions.values() if not ss.handshaken]
        assert self.sock is not None
        for ss in todo:
            self.sock.send(ss.hello_bytes())
        deadline = time.monotonic() + self.timeout_s
        waiting = {ss.stream: ss for ss in todo}
        while waiting:
            msg = self._recv(deadline)
            sid = getattr(msg, "stream", None)
            if isinstance(msg, (wire.HelloAck, wire.ErrorMsg)) and sid in waiting:
                waiting.pop(sid).on_ack(msg)  # an error here raises DaemonRefused: a stream was refused

    def fill(self, frames: dict[str, Any], t: float | None = None) -> dict[str, wire.Message]:
        """Send one capture instant (stream id -> angles, or (angles, observed)) as one bundle and
        wait for every answer: stream id -> FillMsg, Drop, or ErrorMsg (that frame was refused)."""
        unknown = set(frames) - set(self.sessions)
        if unknown:
            raise ValueError(f"streams not opened by this client: {sorted(unknown)[:5]}")
        t = time.time() if t is None else t
        seqs: dict[str, int] = {}
        maps: list[wire.Frame | wire.WireError] = []
        for sid, v in frames.items():
            angles, observed = v if isinstance(v, tuple) else (v, None)
            seqs[sid], f = self.sessions[sid].frame_msg(angles, observed, t)
            maps.append(f)
        data = wire.encode(wire.Bundle(maps))
        for attempt in range(self.retries + 1):
            try:
                self._handshakes()
                assert self.sock is not None
                try:
                    self.sock.send(data, copy=False)
                except zmq.Again:
                    raise TimeoutError from None
                return self._await(seqs)
            except TimeoutError:
                if attempt < self.retries:
                    self.reconnect()
        raise DaemonUnavailable(f"no answer from {self.endpoint} for a bundle of {len(frames)} frame(s) "
                                f"after {self.retries + 1} tries of {self.timeout_s:g} s")

    def _await(self, seqs: dict[str, int]) -> dict[str, wire.Message]:
        out: dict[str, wire.Message] = {}
        deadline = time.monotonic() + self.timeout_s
        while len(out) < len(seqs):
            msg = self._recv(deadline)
            items = msg.items if isinstance(msg, wire.Replies) else [msg]
            for m in items:
                sid = getattr(m, "stream", None)
                if sid in seqs and getattr(m, "seq", None) == seqs[sid]:
                    out[sid] = m
                elif isinstance(m, wire.ErrorMsg) and sid is None and not isinstance(msg, wire.Replies):
                    raise DaemonRefused(m)   # the bundle itself was refused
                # else: an answer to an earlier bundle that timed out, not ours to keep
        return out

    def status(self) -> dict[str, Any]:
        r = control(self.endpoint, "status", timeout_s=self.timeout_s, ctx=self.ctx)
        if not r.ok:
            raise DaemonRefused(wire.ErrorMsg("status", r.error or "status failed"))
        return r.result
