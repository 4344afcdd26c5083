"""asyncio twin of :class:`clients.client.Client` (same session logic, zmq.asyncio socket).

    async with AsyncClient("tcp://127.0.0.1:5555", "actor1", channels=names) as c:
        fill = await c.fill(angles, observed)
"""
from __future__ import annotations

import asyncio
import time
from typing import Any

import zmq
import zmq.asyncio

from clients.client import _DealerLink
from clients.control import decode_reply
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


class AsyncClient(_DealerLink):
    """One stream's connection; every method that talks to the daemon is a coroutine.

    Parameters are those of :class:`clients.client.Client`.
    """

    def __init__(self, endpoint: str, stream: str, channels: list[str] | None = None, model: str | None = None,
                 *, timeout_s: float = DEFAULT_TIMEOUT_S, retries: int = DEFAULT_RETRIES,
                 ctx: zmq.asyncio.Context | None = None, first_seq: int = 0, positions: bool = False):
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be positive (got {timeout_s})")
        self.endpoint = endpoint
        self.session = StreamSession(stream, channels, model, first_seq, positions)
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self._own_ctx = ctx is None
        self.ctx = ctx or zmq.asyncio.Context()
        # the monitor is read without awaiting, through a sync view of the same context
        self._sync_ctx: zmq.Context[Any] = zmq.Context.shadow(self.ctx.underlying)
        self.sock: zmq.asyncio.Socket | None = None
        self._mon: zmq.Socket[Any] | None = None
        self._open()

    def _open(self) -> None:
        # (dealer_socket makes the context's kind of socket: an asyncio one here)
        self.sock = dealer_socket(self.ctx, self.endpoint, self.timeout_s)  # type: ignore[assignment]
        self._mon = open_monitor(self._sync_ctx, self.sock,  # type: ignore[arg-type]
                                 "a" + self.session.stream.encode().hex()[:32])

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: Any) -> None:
        self.close()

    async def _send(self, data: bytes) -> None:
        assert self.sock is not None
        try:
            await asyncio.wait_for(self.sock.send(data), self.timeout_s)
        except (TimeoutError, zmq.Again):
            raise TimeoutError("no daemon connected") from None

    async def recv(self, timeout_s: float | None = None) -> wire.Message | None:
        """The next message from the daemon, or None after ``timeout_s``."""
        assert self.sock is not None
        t = self.timeout_s if timeout_s is None else timeout_s
        if not await self.sock.poll(int(t * 1000), zmq.POLLIN):  # type: ignore[call-arg]
            return None
        return decode_reply(await self.sock.recv())

    async def hello(self) -> wire.HelloAck:
        if self.session.channels is None:
            raise ValueError("this client has no channel list to hand over (channels=None)")
        for attempt in range(self.retries + 1):
            try:
                await self._send(self.session.hello_bytes())
                deadline = time.monotonic() + self.timeout_s
                while True:
                    msg = await self.recv(max(0.0, deadline - time.monotonic()))
                    if msg is None:
                        raise TimeoutError("no hello-ack")
                    if isinstance(msg, (wire.HelloAck, wire.ErrorMsg)):
                        return self.session.on_ack(msg)
            except TimeoutError:
                if attempt == self.retries:
                    break
                self.reconnect()
        raise DaemonUnavailable(f"no answer from {self.endpoint} to the handshake of {self.session.stream!r}")

    async def _ensure_handshake(self) -> None:
        self.session.drain_monitor(self._mon)
        if not self.session.handshaken:
            await self.hello()

    async def send(self, angles: Any, observed: Any = None, t: float | None = None, seq: int | None = None) -> int:
        await self._ensure_handshake()
        seq, data = self.session.frame_bytes(angles, observed, t, seq)
        await self._send(data)
        return seq

    async def fill(self, angles: Any, observed: Any = None, t: float | None = None,
             seq: int | None = None) -> wire.FillMsg | wire.Drop:
        """Send one frame and await its FillMsg or Drop (see Client.fill)."""
        seq, data = self.session.frame_bytes(angles, observed, t, seq)
        for attempt in range(self.retries + 1):
            try:
                await self._ensure_handshake()
                await self._send(data)
                msg = await self._await_seq(seq)
            except TimeoutError:
                if attempt == self.retries:
                    break
                self.reconnect()
                continue
            if isinstance(msg, wire.ErrorMsg):
                if msg.reason in REHELLO_REASONS and self.session.channels is not None and attempt < self.retries:
                    self.session.handshaken = False
                    continue
                raise DaemonRefused(msg)
            assert isinstance(msg, (wire.FillMsg, wire.Drop))  # (_await_seq returns nothing else)
            return msg
        raise DaemonUnavailable(f"no answer from {self.endpoint} for frame {seq} of {self.session.stream!r}")

    async def _await_seq(self, seq: int) -> wire.Message:
        deadline = time.monotonic() + self.timeout_s
        while True:
            msg = await self.recv(max(0.0, deadline - time.monotonic()))
            if msg is None:
                raise TimeoutError(f"frame {seq}")
            if isinstance(msg, (wire.FillMsg, wire.Drop)) and msg.seq == seq:
                return msg
            if isinstance(msg, wire.ErrorMsg) and msg.seq in (seq, None):
                return msg

    async def control(self, cmd: str, stream: str | None = None) -> wire.ControlReply:
        """A control request (status, reset, reload, list-models) on a short-lived socket of its
        own, so its answer never mixes with the stream's pipelined frame answers."""
        s: zmq.asyncio.Socket = dealer_socket(self.ctx, self.endpoint, self.timeout_s)  # type: ignore[assignment]
        try:
            try:
                await asyncio.wait_for(s.send(wire.encode(wire.Control(cmd, stream))), self.timeout_s)
            except (TimeoutError, zmq.Again):
                raise DaemonUnavailable(f"no daemon at {self.endpoint} (control {cmd})") from None
            if not await s.poll(int(self.timeout_s * 1000), zmq.POLLIN):  # type: ignore[call-arg]
                raise DaemonUnavailable(f"no answer from {self.endpoint} to control {cmd} within {self.timeout_s:g} s")
            msg = decode_reply(await s.recv())
        finally:
            s.close(linger=0)
        if isinstance(msg, wire.ErrorMsg):
            raise DaemonRefused(msg)
        if not isinstance(msg, wire.ControlReply):
            raise DaemonRefused(wire.ErrorMsg("unexpected", f"control {cmd} answered with {type(msg).__name__}"))
        return msg

    async def status(self) -> dict[str, Any]:
        r = await self.control("status")
        if not r.ok:
            raise DaemonRefused(wire.ErrorMsg("status", r.error or "status failed"))
        return r.result
