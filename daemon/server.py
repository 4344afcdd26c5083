"""`lacuna serve`'s entry point: :func:`serve` (daemon/loop.py has the daemon; the control
client is clients/control.py).

The daemon's files, in the order a frame meets them (docs: shared/DESIGN.md's data flow):
transport.py (sockets) -> dispatch.py (decode -> session.py) -> tick.py (scheduler.py -> the
fills' encode in wire.py) -> outbox.py (the transport's sending half); loop.py holds the lifecycle
and the loop, control.py the control requests, reload.py reloads, log.py the log.
"""
from __future__ import annotations

from daemon.log import LEVELS, Log
from daemon.loop import Daemon, serve

__all__ = ["LEVELS", "Daemon", "Log", "serve"]
