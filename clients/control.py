"""Control requests (status, reset, reload, list-models) to a daemon: the one client of the control verbs.

:func:`control` opens a short-lived DEALER (a separate socket keeps control answers out of a
stream's pipelined frame answers); :func:`request` asks on a socket the caller already has.
"""
from __future__ import annotations

import time

import msgpack
import zmq

from clients.session import DEFAULT_TIMEOUT_S, DaemonRefused, DaemonUnavailable, dealer_socket
from daemon import wire


def decode_reply(data: bytes) -> wire.Message:
    """Decode an answer from the daemon.

    ``wire.decode`` caps maps at 64 keys and arrays at MAX_CHANNELS (right for untrusted
    input), but a ``status`` reply lists every stream in one map; a daemon's reply is trusted
    and is read without those caps.
    """
    try:
        return wire.decode(data, max_bytes=1 << 26)
    except wire.WireError:
        m = msgpack.unpackb(data, raw=False, strict_map_key=False)
        if isinstance(m, dict) and m.get("type") == "control-reply":
            return wire.ControlReply(str(m.get("cmd")), bool(m.get("ok")), m.get("result") or {}, m.get("error"))
        raise


def request(sock: zmq.Socket[bytes], cmd: str, stream: str | None = None, *,
            timeout_s: float = DEFAULT_TIMEOUT_S, where: str = "the daemon") -> wire.ControlReply:
    """Send one control request on ``sock`` and return its reply, skipping answers to anything else.

    DaemonUnavailable when no reply comes within ``timeout_s``; DaemonRefused on an ``error``."""
    try:
        sock.send(wire.encode(wire.Control(cmd, stream)))
    except zmq.Again:
        raise DaemonUnavailable(f"no answer from {where} to control {cmd}: no daemon connected "
                                f"(is `lacuna serve` running?)") from None
    poller = zmq.Poller()
    poller.register(sock, zmq.POLLIN)
    deadline = time.monotonic() + timeout_s
    while True:
        left = deadline - time.monotonic()
        if left <= 0 or not poller.poll(int(left * 1000)):
            raise DaemonUnavailable(f"no answer from {where} to control {cmd} within {timeout_s:g} s "
                                    f"(is `lacuna serve` running?)")
        msg = decode_reply(sock.recv_multipart()[-1])
        if isinstance(msg, wire.ControlReply) and msg.cmd == cmd:
            return msg
        if isinstance(msg, wire.ErrorMsg) and msg.seq is None:
            raise DaemonRefused(msg)
        # an answer to a frame sent earlier on this socket: not ours


def control(endpoint: str, cmd: str, stream: str | None = None, *, timeout_s: float = DEFAULT_TIMEOUT_S,
            ctx: zmq.Context[zmq.Socket[bytes]] | None = None,
            curve: tuple[str, str] | None = None) -> wire.ControlReply:
    """One control request on a short-lived DEALER to ``endpoint``; ``curve`` = (client
    .key_secret file, the daemon's public .key file) for a daemon with [security] keys."""
    own = ctx is None
    c = ctx if ctx is not None else zmq.Context()
    s = dealer_socket(c, endpoint, timeout_s, curve)
    try:
        return request(s, cmd, stream, timeout_s=timeout_s, where=endpoint)
    finally:
        s.close(linger=0)
        if own:
            c.term()

