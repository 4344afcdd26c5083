"""sd_notify without libsystemd: datagrams to $NOTIFY_SOCKET.  Does nothing when it is unset.

READY=1 once sockets are bound and models loaded; STATUS=... free text; WATCHDOG=1 every half
of $WATCHDOG_USEC (from the main loop, so a stuck loop stops the pings and systemd restarts
the service); RELOADING=1 (with MONOTONIC_USEC, as systemd >= 253 wants) ... READY=1 around a
reload; STOPPING=1 on the way out.
"""
from __future__ import annotations

import os
import socket
import time
from collections.abc import Mapping


class Notifier:
    def __init__(self, env: Mapping[str, str] | None = None):
        env = os.environ if env is None else env
        addr = env.get("NOTIFY_SOCKET", "")
        self.addr: str | None = None
        self.sock: socket.socket | None = None
        if addr and addr[0] in "/@":
            self.addr = "\0" + addr[1:] if addr[0] == "@" else addr
            self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            self.sock.setblocking(False)
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        ok_pid = not pid or (pid.isdigit() and int(pid) == os.getpid())
        self.watchdog_s = int(usec) / 2e6 if usec.isdigit() and int(usec) > 0 and ok_pid else None
        self._next_ping = 0.0
        self.errors = 0

    @property
    def enabled(self) -> bool:
        return self.sock is not None

    def send(self, *lines: str) -> None:
        if self.sock is None or self.addr is None:
            return
        try:
            self.sock.sendto("\n".join(lines).encode(), self.addr)
        except OSError:
            self.errors += 1  # systemd gone or socket full: never let notification stop serving

    def ready(self, status: str = "") -> None:
        self.send("READY=1", *([f"STATUS={status}"] if status else []))

    def status(self, text: str) -> None:
        self.send(f"STATUS={text}")

    def reloading(self) -> None:
        self.send("RELOADING=1", f"MONOTONIC_USEC={time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000}")

    def stopping(self) -> None:
        self.send("STOPPING=1")

    def watchdog_due(self, now: float) -> float | None:
        """Seconds until the next watchdog ping (None if no watchdog); pings when due."""
        if self.watchdog_s is None:
            return None
        if now >= self._next_ping:
            self.send("WATCHDOG=1")
            self._next_ping = now + self.watchdog_s
        return self._next_ping - now

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None
