"""`lacuna serve`'s entry points: :func:`serve` (daemon/loop.py has the daemon) and the
``control`` client.

The daemon's files, in the order a frame meets them (docs: shared/DESIGN.md's data flow):
transport.py (sockets) -> dispatch.py (decode -> session.py) -> tick.py (scheduler.py -> the
fills' encode in wire.py) -> transport.py; loop.py holds the lifecycle and the loop, control.py
the control requests, reload.py reloads, log.py the log.
"""
from __future__ import annotations

import zmq

from daemon import security, wire
from daemon.log import LEVELS, Log
from daemon.loop import Daemon, serve

__all__ = ["LEVELS", "Daemon", "Log", "control", "serve"]


def control(endpoint: str, cmd: str, stream: str | None = None, timeout_s: float = 5.0,
            curve: tuple[str, str] | None = None) -> wire.ControlReply:
    """One control request over a DEALER socket (what `lacuna status` uses).  ``curve`` =
    (client .key_secret file, daemon's public .key file) for a daemon with [security] keys."""
    ctx = zmq.Context()
    s = ctx.socket(zmq.DEALER)
    s.setsockopt(zmq.LINGER, 0)
    try:
        if curve is not None:
            security.configure_client(s, *curve)
        s.connect(endpoint)
        s.send(wire.encode(wire.Control(cmd, stream)))
        if not s.poll(int(timeout_s * 1000)):
            raise TimeoutError(f"no answer from {endpoint} within {timeout_s:g} s (is `lacuna serve` running?)")
        m = wire.decode(s.recv(), 64 << 20)
        if isinstance(m, wire.ErrorMsg):
            raise ValueError(f"{endpoint} refused {cmd}: {m.reason}: {m.detail}")
        if not isinstance(m, wire.ControlReply):
            raise ValueError(f"{endpoint} answered {cmd} with a {type(m).__name__}")
        return m
    finally:
        s.close()
        ctx.term()


