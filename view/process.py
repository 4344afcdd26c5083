"""Start ``lacuna view`` as a real subprocess and learn its address (for tests and benchmarks)."""
from __future__ import annotations

import os
import re
import select
import signal
import subprocess
import sys
import time
from collections.abc import Sequence

from lacuna.errors import LacunaError

START_TIMEOUT_S = 30.0
STOP_TIMEOUT_S = 10.0
URL_RE = re.compile(r"lacuna view: (http://\S+)")


class ViewProcess:
    """``lacuna view ARGS --listen 127.0.0.1:0``; :attr:`url` once it printed its address."""

    def __init__(self, args: Sequence[str], env: dict[str, str] | None = None, cwd: str | None = None):
        self.args = list(args)
        self.cwd = cwd  # (a directory holding another checkout's view/ package, to run that one)
        self.env = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
        self.proc: subprocess.Popen | None = None
        self.url = ""
        self.stderr = ""

    def start(self, timeout_s: float = START_TIMEOUT_S) -> ViewProcess:
        self.proc = subprocess.Popen([sys.executable, "-m", "lacuna.cli", "view", *self.args, "--listen", "127.0.0.1:0"],
                                     stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     env=self.env, cwd=self.cwd, start_new_session=True)
        assert self.proc.stdout is not None
        deadline = time.monotonic() + timeout_s
        out = b""
        while time.monotonic() < deadline:
            r, _, _ = select.select([self.proc.stdout], [], [], 0.2)
            if r:
                chunk = os.read(self.proc.stdout.fileno(), 4096)
                out += chunk
                m = URL_RE.search(out.decode(errors="replace"))
                if m:
                    self.url = m.group(1)
                    return self
                if not chunk:
                    break
            if self.proc.poll() is not None and not r:
                break
        self.stop()
        raise LacunaError(f"lacuna view did not start: {out.decode(errors='replace')} {self.stderr}".strip())

    def stop(self) -> int | None:
        p = self.proc
        if p is None:
            return None
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(STOP_TIMEOUT_S)
        if p.stderr is not None and not p.stderr.closed:
            self.stderr = p.stderr.read().decode(errors="replace")
            p.stderr.close()
        if p.stdout is not None and not p.stdout.closed:
            p.stdout.close()
        return p.returncode

    def __enter__(self) -> ViewProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
