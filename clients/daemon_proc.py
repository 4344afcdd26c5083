"""Start ``lacuna serve`` as a real subprocess on loopback, wait until it answers, stop it cleanly.

Used by ``lacuna bench --model``, ``lacuna demo`` and the tests.  The daemon's config is written
to a TOML file in a working directory; its stderr (structured logs) goes to ``daemon.log`` there,
so a daemon that dies at start-up is reported with the tail of its own words.
"""
from __future__ import annotations

import atexit
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from clients.client import control
from clients.session import DaemonUnavailable
from lacuna.errors import LacunaError

START_TIMEOUT_S = 60.0  # loading big models takes a while on a busy 2-core machine
STOP_TIMEOUT_S = 10.0  # SIGTERM drains; after this, SIGKILL
POLL_S = 0.1


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free right now on ``host`` (the kernel picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def free_udp_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def write_config(path: str | os.PathLike, cfg: dict[str, dict[str, Any]]) -> None:
    """Write a two-level TOML document ({section: {key: value}}; dotted sections allowed)."""
    lines = []
    for section, keys in cfg.items():
        lines.append(f"[{section}]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in keys.items()]
        lines.append("")
    Path(path).write_text("\n".join(lines))


class DaemonProcess:
    """A ``lacuna serve`` subprocess.

    Parameters
    ----------
    models : {name: model file path} or {name: {"builtin": "passthrough", "channels": [...]}}.
    default_model : name of the model streams get without asking.
    workdir : where the config and log go (a fresh temporary directory by default).
    port : ROUTER port (a free one by default); keep it to restart on the same address.
    daemon, zmq, osc : extra keys for those config sections.
    """

    def __init__(self, models: dict[str, Any], default_model: str | None = None, *, workdir: str | None = None,
                 port: int | None = None, daemon: dict[str, Any] | None = None, zmq: dict[str, Any] | None = None,
                 osc: dict[str, Any] | None = None):
        self.models = models
        self.default_model = default_model or next(iter(models))
        self.workdir = Path(workdir or tempfile.mkdtemp(prefix="lacuna-daemon-"))
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.port = port or free_port()
        self.endpoint = f"tcp://127.0.0.1:{self.port}"
        self.daemon_opts = dict(daemon or {})
        self.zmq_opts = dict(zmq or {})
        self.osc_opts = dict(osc or {})
        self.config_path = self.workdir / "lacuna.toml"
        self.log_path = self.workdir / "daemon.log"
        self.proc: subprocess.Popen | None = None
        self._log = None
        atexit.register(self.stop)

    def config(self) -> dict[str, dict[str, Any]]:
        cfg: dict[str, dict[str, Any]] = {"daemon": {"default_model": self.default_model, **self.daemon_opts},
                                          "zmq": {"router": self.endpoint, **self.zmq_opts}}
        if self.osc_opts:
            cfg["osc"] = self.osc_opts
        for name, spec in self.models.items():
            if isinstance(spec, (str, os.PathLike)):
                cfg[f"models.{name}"] = {"file": os.path.abspath(os.fspath(spec))}  # the config's dir is not ours
            else:
                cfg[f"models.{name}"] = dict(spec)
        return cfg

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc else None

    def start(self, timeout_s: float = START_TIMEOUT_S) -> "DaemonProcess":
        """Start and wait until the daemon answers a status request; LacunaError if it does not."""
        if self.proc and self.proc.poll() is None:
            return self
        write_config(self.config_path, self.config())
        self._log = open(self.log_path, "ab")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env.pop("NOTIFY_SOCKET", None)  # not ours to notify
        self.proc = subprocess.Popen([sys.executable, "-m", "lacuna.cli", "serve", "--config", str(self.config_path)],
                                     stdin=subprocess.DEVNULL, stdout=self._log, stderr=self._log, env=env,
                                     # own session: a terminal's Ctrl-C reaches only us, and we stop
                                     # the daemon with SIGTERM (drain) in stop()
                                     start_new_session=True)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise LacunaError(f"the daemon exited at start-up with status {self.proc.returncode}: {self.log_tail()}")
            try:
                control(self.endpoint, "status", timeout_s=0.5)
                return self
            except DaemonUnavailable:
                time.sleep(POLL_S)
        self.stop()
        raise LacunaError(f"the daemon did not answer on {self.endpoint} within {timeout_s:g} s: {self.log_tail()}")

    def log_tail(self, n: int = 8) -> str:
        try:
            lines = self.log_path.read_text(errors="replace").strip().splitlines()
        except OSError:
            return "(no log)"
        return " | ".join(lines[-n:]) or "(empty log)"

    def kill(self) -> None:
        """SIGKILL, as a crash would (tests of reconnect)."""
        if self.proc and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(STOP_TIMEOUT_S)

    def stop(self) -> int | None:
        """SIGTERM (the daemon drains and exits), SIGKILL after STOP_TIMEOUT_S; returns the exit status."""
        p = self.proc
        if p is None:
            return None
        if p.poll() is None:
            try:
                p.send_signal(signal.SIGTERM)
                p.wait(STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(STOP_TIMEOUT_S)
            except KeyboardInterrupt:  # a second Ctrl-C while draining: do not leave it behind
                p.kill()
                p.wait(STOP_TIMEOUT_S)
                raise
        if self._log:
            self._log.close()
            self._log = None
        return p.returncode

    def __enter__(self) -> "DaemonProcess":
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of a process, from /proc/<pid>/stat (Linux; None elsewhere)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            stat = fh.read()
    except OSError:
        return None
    # the command name (field 2) may contain spaces and parentheses; fields resume after the last ')'
    fields = stat[stat.rindex(")") + 2:].split()
    utime, stime = int(fields[11]), int(fields[12])  # fields 14 and 15 of proc(5)
    return (utime + stime) / os.sysconf("SC_CLK_TCK")


def rss_bytes(pid: int) -> int | None:
    """Resident set size from /proc/<pid>/statm (for 'memory stays flat' checks)."""
    try:
        with open(f"/proc/{pid}/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:
        return None
