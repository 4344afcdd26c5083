"""Start ``lacuna serve`` as a real child process, wait until it is ready, read its log, stop it.

The one daemon harness of ``lacuna bench --serve``/``replay --serve``/``demo``, the benches and the tests.

* ``DaemonProcess("lacuna.toml")`` serves a config file you wrote (clients.configfile writes one);
  ``DaemonProcess({"walk": "walk.npz"}, daemon={...}, zmq={...})`` writes one for those models on
  a free loopback port, in ``workdir`` (a fresh temporary directory by default).
* ``start()`` waits for the daemon's ``ready`` log line, which carries the bound endpoints
  (``endpoints``), so configs may bind ``tcp://127.0.0.1:*`` and port 0.
* The daemon's stderr (JSON lines) and stdout go to a log file, never through a pipe the test
  process must drain: a daemon that logs 10^5 rejections costs the sender nothing.
  ``wait_for(event, **fields)`` returns the next such record not returned before.
* ``stop()`` sends SIGTERM (the daemon drains), SIGKILL after ``STOP_TIMEOUT_S``: never hangs.
* Every child carries its owner in its environment (``OWNER_ENV``: the starting process's pid and
  start time).  A harness process that dies without stopping its daemon (SIGKILL, a CI timeout)
  leaves the daemon behind, stopped forever if it was held stopped; ``sweep_orphans()`` finds such
  children of harnesses no longer alive and kills them (the test suite calls it at start).
"""
from __future__ import annotations

import atexit
import json
import os
import signal as _signal
import subprocess
import sys
import tempfile
import time
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from clients.configfile import Config, free_port, write_config
from lacuna.errors import LacunaError

# The first start after an install compiles the numba kernels in the models' warm-up (the daemon
# logs ``loading`` and ``loaded`` per model): 53 s and 64 s for the demo's default on two fresh clones
# here, over 60 s on CI's machine (stop 38's run failed there).  Cached afterwards (~2 s).
START_TIMEOUT_S = 300.0
STOP_TIMEOUT_S = 10.0  # SIGTERM drains; after this, SIGKILL
POLL_S = 0.01
OWNER_ENV = "LACUNA_HARNESS_OWNER"  # "<pid>:<start time in clock ticks>" of the process that started the daemon


class DaemonStartError(LacunaError, RuntimeError):
    """The daemon exited before it was ready (the message carries the tail of its log)."""


class DaemonStartTimeout(DaemonStartError, TimeoutError):
    """The daemon did not log ``ready`` within the start timeout."""


class DaemonProcess:
    """A ``lacuna serve`` child.

    Parameters
    ----------
    config : a config file's path, or {name: model file path | {"builtin": "passthrough", ...}}
        to serve those models from a config this harness writes.
    default_model : (with models) the model streams get without asking; the first by default.
    workdir : (with models) where the config and log go.
    port : (with models) the ROUTER port, a free one by default; kept across restarts.
    daemon, zmq, osc, metrics : (with models) extra keys of those config sections.
    env : extra environment of the child; log_path : where its output goes
        (``daemon.log`` in workdir with models, a fresh file beside the config otherwise).
    python : the interpreter that runs ``-m lacuna.cli serve``.
    argv : what runs instead of ``python -m lacuna.cli serve --config`` (the config's path is appended),
        e.g. a benchmark's wrapper around ``daemon.loop.serve`` that times its parts.
    """

    def __init__(self, config: str | os.PathLike[str] | Mapping[str, Any], default_model: str | None = None, *,
                 env: Mapping[str, str] | None = None, log_path: str | os.PathLike[str] | None = None,
                 workdir: str | os.PathLike[str] | None = None, port: int | None = None,
                 daemon: dict[str, Any] | None = None, zmq: dict[str, Any] | None = None,
                 osc: dict[str, Any] | None = None, metrics: dict[str, Any] | None = None,
                 python: str = sys.executable, argv: Sequence[str] | None = None):
        self.env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.env.pop("NOTIFY_SOCKET", None)  # not ours to notify, unless the caller says so
        self.env.update(env or {})
        self.env[OWNER_ENV] = _owner_tag(os.getpid())
        self.python = python
        self.argv = list(argv) if argv is not None else [python, "-m", "lacuna.cli", "serve", "--config"]
        self._cfg: Config | None = None
        if isinstance(config, Mapping):
            self.workdir = Path(workdir or tempfile.mkdtemp(prefix="lacuna-daemon-"))
            self.workdir.mkdir(parents=True, exist_ok=True)
            self.port = port or free_port()
            self.endpoint = f"tcp://127.0.0.1:{self.port}"
            self._cfg = _models_config(config, default_model, self.endpoint, daemon, zmq, osc, metrics)
            self.config_path = self.workdir / "lacuna.toml"
            write_config(self.config_path, self._cfg)
            self.log_path = Path(log_path or self.workdir / "daemon.log")
        else:
            self.config_path = Path(config)
            self.workdir = self.config_path.parent
            self.endpoint = ""
            if log_path is None:
                fd, name = tempfile.mkstemp(prefix="daemon-", suffix=".log", dir=self.workdir)
                os.close(fd)
                log_path = name
            self.log_path = Path(log_path)
        self.proc: subprocess.Popen[bytes] | None = None
        self.endpoints: dict[str, Any] = {}
        self._log: list[dict[str, Any]] = []  # every record read so far, across restarts
        self._seen: set[int] = set()  # indices into log that wait_for has returned
        self._offset = self.log_path.stat().st_size if self.log_path.exists() else 0
        self._partial = b""
        self._run_from = 0  # index in log of this run's first record
        atexit.register(self.stop)

    # ---- configuration ------------------------------------------------------------------------
    def config(self) -> Config:
        """The config served ({section: {key: value}}, dotted sections as written)."""
        if self._cfg is not None:
            return self._cfg
        with open(self.config_path, "rb") as fh:
            doc = tomllib.load(fh)
        flat: Config = {}
        for sec, body in doc.items():
            if sec == "models" or sec == "streams":
                flat.update({f"{sec}.{k}": dict(v) for k, v in body.items()})
            else:
                flat[sec] = dict(body)
        return flat

    @property
    def zmq_opts(self) -> dict[str, Any]:
        return self.config().get("zmq", {})

    @property
    def osc_opts(self) -> dict[str, Any]:
        return self.config().get("osc", {})

    # ---- lifecycle ----------------------------------------------------------------------------
    def start(self, timeout_s: float = START_TIMEOUT_S) -> DaemonProcess:
        """Start (unless running) and wait for the ``ready`` line; DaemonStartError if it does not come."""
        if self.alive():
            return self
        self._pull()
        self._seen.update(range(len(self._log)))  # a restart waits for its own records only
        self._run_from = len(self._log)
        with open(self.log_path, "ab") as fh:
            self.proc = subprocess.Popen([*self.argv, str(self.config_path)],
                                         stdin=subprocess.DEVNULL, stdout=fh, stderr=fh, env=self.env,
                                         # own session: a terminal's Ctrl-C reaches only us, and stop()
                                         # drains the daemon with SIGTERM
                                         start_new_session=True)
        try:
            rec = self.wait_for("ready", timeout_s)
        except TimeoutError:
            self.stop()
            raise DaemonStartTimeout(f"the daemon did not log ready within {timeout_s:g} s: {self.log_tail()}") from None
        except RuntimeError:
            raise DaemonStartError(f"the daemon exited at start-up with status {self.returncode}: "
                                   f"{self.log_tail()}") from None
        self.endpoints = dict(rec.get("endpoints") or {})
        if not self.endpoint and isinstance(self.endpoints.get("router"), str):
            self.endpoint = self.endpoints["router"]
        return self

    @property
    def pid(self) -> int:
        assert self.proc is not None, "the daemon was never started"
        return self.proc.pid

    @property
    def returncode(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def signal(self, sig: int) -> None:
        assert self.proc is not None
        self.proc.send_signal(sig)

    def kill(self) -> None:
        """SIGKILL, as a crash would (tests of reconnect)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(STOP_TIMEOUT_S)

    def stop(self, sig: int = _signal.SIGTERM, timeout_s: float = STOP_TIMEOUT_S) -> int | None:
        """Signal (SIGTERM: the daemon drains and exits), SIGKILL after ``timeout_s``; the exit status.
        A daemon held stopped (SIGSTOP: a starved soak, a debugger) is continued after the signal, so
        it drains and exits rather than waiting out ``timeout_s`` for its SIGKILL; without that, a
        run interrupted while its daemon was stopped left a stopped ``lacuna serve`` behind."""
        p = self.proc
        if p is None:
            return None
        if p.poll() is None:
            try:
                p.send_signal(sig)
                if sig != _signal.SIGSTOP:
                    p.send_signal(_signal.SIGCONT)  # a no-op for a running daemon
                p.wait(timeout_s)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(STOP_TIMEOUT_S)
            except KeyboardInterrupt:  # a second Ctrl-C while draining: do not leave it behind
                p.kill()
                p.wait(STOP_TIMEOUT_S)
                raise
        return p.returncode

    def __enter__(self) -> DaemonProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ---- the log ------------------------------------------------------------------------------
    def _pull(self) -> int:
        """Parse the complete lines logged since the last call into ``log``; how many records came."""
        try:
            with open(self.log_path, "rb") as fh:
                fh.seek(self._offset)
                data = fh.read()
        except OSError:
            return 0
        self._offset += len(data)
        data = self._partial + data
        *lines, self._partial = data.split(b"\n")
        n = len(self._log)
        for line in lines:
            try:
                rec = json.loads(line)
            except ValueError:
                continue
            if isinstance(rec, dict):
                self._log.append(rec)
        return len(self._log) - n

    def records(self) -> list[dict[str, Any]]:
        """Every JSON record logged so far (across restarts)."""
        self._pull()
        return self._log

    @property
    def log(self) -> list[dict[str, Any]]:
        """The same, read afresh at each access."""
        return self.records()

    def wait_for(self, event: str, timeout_s: float = 10.0, **match: Any) -> dict[str, Any]:
        """The first record of this run with ``event`` (and these fields) not returned before.

        TimeoutError after ``timeout_s``; RuntimeError if the daemon exits first."""
        deadline = time.monotonic() + timeout_s
        i = self._run_from
        while True:
            self._pull()
            for j in range(i, len(self._log)):
                rec = self._log[j]
                if j not in self._seen and rec.get("event") == event and all(rec.get(k) == v for k, v in match.items()):
                    self._seen.add(j)
                    return rec
            i = len(self._log)
            if self.proc is not None and self.proc.poll() is not None and not self._pull():
                raise RuntimeError(f"daemon exited ({self.proc.returncode}) before logging {event!r}:\n"
                                   f"{self.tail()}")
            if time.monotonic() > deadline:
                raise TimeoutError(f"daemon did not log {event!r} within {timeout_s} s; log tail:\n{self.tail()}")
            time.sleep(POLL_S)

    def tail(self, n: int = 15) -> str:
        try:
            with open(self.log_path, "rb") as fh:
                return b"".join(fh.readlines()[-n:]).decode(errors="replace")
        except OSError:
            return ""

    def log_tail(self, n: int = 8) -> str:
        """The last ``n`` log lines on one line (for an error message)."""
        return " | ".join(self.tail(n).strip().splitlines()) or "(empty log)"

    # ---- resources ----------------------------------------------------------------------------
    def rss_kib(self) -> int:
        """Resident set size from /proc (VmRSS), KiB."""
        with open(f"/proc/{self.pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
        raise RuntimeError("no VmRSS")

    def cpu_s(self) -> float:
        """utime + stime of the daemon, seconds."""
        c = cpu_seconds(self.pid)
        if c is None:
            raise RuntimeError(f"no /proc/{self.pid}/stat")
        return c


def _models_config(models: Mapping[str, Any], default_model: str | None, router: str, daemon: dict[str, Any] | None,
                   zmq: dict[str, Any] | None, osc: dict[str, Any] | None,
                   metrics: dict[str, Any] | None = None) -> Config:
    cfg: Config = {"daemon": {"default_model": default_model or next(iter(models)), **(daemon or {})},
                   "zmq": {"router": router, **(zmq or {})}}
    if osc:
        cfg["osc"] = dict(osc)
    if metrics:
        cfg["metrics"] = dict(metrics)
    for name, spec in models.items():
        if isinstance(spec, (str, os.PathLike)):
            cfg[f"models.{name}"] = {"file": os.path.abspath(os.fspath(spec))}  # the config's dir is not ours
        else:
            cfg[f"models.{name}"] = dict(spec)
    return cfg


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


# ---- orphans --------------------------------------------------------------------------------------
def _start_ticks(pid: int) -> str | None:
    """A process's start time (field 22 of /proc/PID/stat), None if there is no such process: with
    the pid it names one process, whatever pid reuse does later."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def _owner_tag(pid: int) -> str:
    return f"{pid}:{_start_ticks(pid)}"


def _owner_of(pid: int) -> str | None:
    """The OWNER_ENV tag in a lacuna serve's environment, None for any other process (or one not ours
    to read)."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            argv = fh.read().split(b"\0")
        if b"lacuna.cli" not in argv or b"serve" not in argv:
            return None
        with open(f"/proc/{pid}/environ", "rb") as fh:
            env = fh.read().split(b"\0")
    except OSError:
        return None
    key = OWNER_ENV.encode() + b"="
    for kv in env:
        if kv.startswith(key):
            return kv[len(key):].decode(errors="replace")
    return None


def orphans() -> list[int]:
    """Pids of ``lacuna serve`` processes started by a harness whose process is gone."""
    found = []
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        tag = _owner_of(int(name))
        if tag is None:
            continue
        owner, _, ticks = tag.partition(":")
        if not owner.isdigit() or _start_ticks(int(owner)) != ticks:
            found.append(int(name))
    return found


def sweep_orphans() -> list[int]:
    """SIGKILL every orphaned harness daemon (``orphans()``; SIGKILL ends a stopped process too);
    the pids killed.  A daemon started by a live process, or by hand without the harness, is never
    touched."""
    killed = []
    for pid in orphans():
        try:
            os.kill(pid, _signal.SIGKILL)
            killed.append(pid)
        except ProcessLookupError:
            pass
    return killed
