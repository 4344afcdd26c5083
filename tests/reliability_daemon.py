"""A real `lacuna serve` process for the reliability tests, and the small tools around it.

Unlike daemon.loadgen.DaemonProcess (which parses every log line in the test process), the
daemon's stderr goes to a file here: the fuzz test makes the daemon log ~10^5 rejections and
the test process needs its CPU for sending.  Ports are chosen up front (not ``:*``) so that a
restarted daemon comes back on the same endpoints and clients can reconnect to it.

Everything has a timeout; ``stop()`` kills what does not exit, so teardown never hangs.
"""
from __future__ import annotations

import json
import os
import signal as _signal
import socket
import subprocess
import sys
import threading
import time
from typing import Any

import zmq

from daemon import wire

READY_TIMEOUT_S = 60.0
RECV_MS = 5000


def free_port(kind: int = socket.SOCK_STREAM, host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def write_config(path, models: dict[str, dict[str, Any]], *, router: str | None = None, pull: bool = False,
                 pub: bool = True, osc: bool = False, daemon: dict[str, Any] | None = None,
                 extra: str = "") -> dict[str, Any]:
    """Write a TOML config on fixed free loopback ports; returns the endpoints it names."""
    ep: dict[str, Any] = {"router": router or f"tcp://127.0.0.1:{free_port()}"}
    # (a generous budget: with overdue = "drop", the default, a frame a stall of the test machine
    # holds past the budget is answered `overdue`, and these tests are about other things)
    d = {"budget_ms": 250.0, "idle_timeout_s": 3600, **(daemon or {})}
    lines = ["[daemon]"] + [f"{k} = {json.dumps(v)}" for k, v in d.items()]
    for name, spec in models.items():
        lines.append(f"[models.{name}]")
        lines += [f"{k} = {json.dumps(v)}" for k, v in spec.items()]
    lines += ["[zmq]", f'router = "{ep["router"]}"']
    if pull:
        ep["pull"] = f"tcp://127.0.0.1:{free_port()}"
        lines.append(f'pull = "{ep["pull"]}"')
    if pub or pull:
        ep["pub"] = f"tcp://127.0.0.1:{free_port()}"
        lines.append(f'pub = "{ep["pub"]}"')
    if osc:
        ep["osc"] = ("127.0.0.1", free_port(socket.SOCK_DGRAM))
        lines += ["[osc]", f'listen = "127.0.0.1:{ep["osc"][1]}"']
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n" + extra)
    return ep


class Daemon:
    """One `python -m lacuna.cli serve` child; stderr (JSON lines) appended to ``log_path``."""

    def __init__(self, config: str, log_path: str, env: dict[str, str] | None = None):
        self.config = str(config)
        self.log_path = str(log_path)
        self.env = {**os.environ, **(env or {})}
        self.proc: subprocess.Popen | None = None
        self._offset = 0  # log bytes already scanned by wait_for

    def start(self, timeout_s: float = READY_TIMEOUT_S) -> "Daemon":
        with open(self.log_path, "ab") as fh:
            self._offset = fh.tell()
            self.proc = subprocess.Popen([sys.executable, "-m", "lacuna.cli", "serve", "--config", self.config],
                                         stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=fh, env=self.env)
        self.wait_for("ready", timeout_s)
        return self

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def records(self, since: int = 0) -> list[dict[str, Any]]:
        out = []
        with open(self.log_path, "rb") as fh:
            fh.seek(since)
            for line in fh:
                try:
                    out.append(json.loads(line))
                except ValueError:
                    continue
        return out

    def wait_for(self, event: str, timeout_s: float = 10.0, **match: Any) -> dict[str, Any]:
        """Next log record (after the last one found) with this event and fields."""
        deadline = time.monotonic() + timeout_s
        buf = b""
        with open(self.log_path, "rb") as fh:
            fh.seek(self._offset)
            while True:
                chunk = fh.readline()
                if chunk:
                    buf += chunk
                    if not buf.endswith(b"\n"):
                        continue
                    line, buf = buf, b""
                    self._offset = fh.tell()
                    try:
                        rec = json.loads(line)
                    except ValueError:
                        continue
                    if rec.get("event") == event and all(rec.get(k) == v for k, v in match.items()):
                        return rec
                    continue
                if time.monotonic() > deadline:
                    raise TimeoutError(f"daemon did not log {event!r} within {timeout_s} s; log tail:\n{self.tail()}")
                if self.proc is not None and self.proc.poll() is not None and not chunk:
                    raise RuntimeError(f"daemon exited ({self.proc.returncode}) before logging {event!r}:\n{self.tail()}")
                time.sleep(0.01)

    def tail(self, n: int = 15) -> str:
        try:
            with open(self.log_path, "rb") as fh:
                return b"".join(fh.readlines()[-n:]).decode(errors="replace")
        except OSError:
            return ""

    def rss_kib(self) -> int:
        """Resident set size from /proc (VmRSS), KiB."""
        with open(f"/proc/{self.pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
        raise RuntimeError("no VmRSS")

    def cpu_s(self) -> float:
        """utime + stime of the daemon, seconds."""
        with open(f"/proc/{self.pid}/stat") as fh:
            f = fh.read().rsplit(")", 1)[1].split()
        return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")

    def signal(self, sig: int) -> None:
        assert self.proc is not None
        self.proc.send_signal(sig)

    def stop(self, sig: int = _signal.SIGTERM, timeout_s: float = 10.0) -> int | None:
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        return self.proc.returncode


class Supervisor:
    """What systemd's Restart=on-failure does, as a thread: when the daemon dies with a failure
    status (or a signal), start it again after ``restart_s``.  ``restarts`` counts them."""

    def __init__(self, daemon: Daemon, restart_s: float = 0.2):
        self.daemon = daemon
        self.restart_s = restart_s
        self.restarts = 0
        self.errors: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="supervisor", daemon=True)

    def start(self) -> "Supervisor":
        self.daemon.start()
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            p = self.daemon.proc
            assert p is not None
            try:
                rc = p.wait(0.05)
            except subprocess.TimeoutExpired:
                continue
            if self._stop.is_set() or rc == 0:
                return  # clean exit: on-failure does not restart
            time.sleep(self.restart_s)
            try:
                self.daemon.start()
                self.restarts += 1
            except (RuntimeError, TimeoutError) as e:
                self.errors.append(str(e))
                return

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10)
        self.daemon.stop()


# ---- client side ----------------------------------------------------------------------------------
class Sockets:
    """Tracks every socket it makes; ``close()`` closes them with linger 0 and terms the context."""

    def __init__(self) -> None:
        self.ctx = zmq.Context()
        self.socks: list[zmq.Socket] = []

    def make(self, kind: int, connect: str | None = None) -> zmq.Socket:
        s = self.ctx.socket(kind)
        s.setsockopt(zmq.LINGER, 0)
        self.socks.append(s)
        if connect:
            s.connect(connect)
        return s

    def close(self) -> None:
        for s in self.socks:
            s.close(0)
        self.ctx.term()


def recv_msg(sock: zmq.Socket, timeout_ms: int = RECV_MS) -> wire.Message:
    if not sock.poll(timeout_ms):
        raise TimeoutError(f"no answer within {timeout_ms} ms")
    return wire.decode(sock.recv_multipart()[-1], 64 << 20)


def control(sock: zmq.Socket, cmd: str, stream: str | None = None, timeout_ms: int = RECV_MS) -> dict[str, Any]:
    """A control request on a DEALER that carries nothing else; returns the result map."""
    sock.send(wire.encode(wire.Control(cmd, stream)))
    while True:
        m = recv_msg(sock, timeout_ms)
        if isinstance(m, wire.ControlReply) and m.cmd == cmd:
            if not m.ok and cmd != "reload":
                raise RuntimeError(f"{cmd} refused: {m.error}")
            return {**m.result, "_ok": m.ok, "_error": m.error}


def status(ctx_or_sockets: Sockets, endpoint: str, timeout_ms: int = RECV_MS) -> dict[str, Any]:
    """Status over a fresh DEALER (so it never mixes with a test's own traffic)."""
    s = ctx_or_sockets.make(zmq.DEALER, endpoint)
    try:
        return control(s, "status", timeout_ms=timeout_ms)
    finally:
        s.close(0)
        ctx_or_sockets.socks.remove(s)


def udp_queue(port: int) -> tuple[int, int]:
    """(rx_queue bytes, kernel drops) of the UDP socket bound to 127.0.0.1:port, from /proc/net/udp.

    The drops column is the kernel's count of datagrams it threw away because that socket's
    receive buffer was full: exactly the datagrams the daemon never saw."""
    want = f"0100007F:{port:04X}"
    with open("/proc/net/udp") as fh:
        next(fh)
        for line in fh:
            f = line.split()
            if f[1] == want:
                return int(f[4].split(":")[1], 16), int(f[-1])
    raise LookupError(f"no UDP socket on 127.0.0.1:{port}")


class LockStep(threading.Thread):
    """A capture plugin in a thread: send frame n, wait for its answer, send n+1.

    With ``reconnect_ms``, a request unanswered that long is sent again on a fresh socket (what
    a plugin does when the daemon restarts); ``retries`` counts those.  ``answers`` maps seq ->
    the answer finally received; ``sent_at``/``got_at`` are perf_counter stamps.
    """

    def __init__(self, endpoint: str, sid: str, frames, reconnect_ms: int | None = None, timeout_ms: int = 20_000,
                 hello: list[str] | None = None, curve: tuple[str, str] | None = None):
        super().__init__(name=f"lockstep-{sid}", daemon=True)
        self.endpoint, self.sid, self.frames = endpoint, sid, frames
        self.reconnect_ms, self.timeout_ms, self.hello = reconnect_ms, timeout_ms, hello
        self.stop_flag = threading.Event()
        self.answers: dict[int, wire.Message] = {}
        self.got_at: dict[int, float] = {}
        self.retries = 0
        self.retried: set[int] = set()  # seqs sent again after a timeout
        self.problems: list[str] = []
        self.t_of: dict[int, float] = {}  # capture timestamp sent with each seq
        self.t_fn = lambda seq: seq / 120.0
        self.claim = f"lockstep-{sid}-{os.getpid()}-{id(self):x}"

    def _socket(self, ctx: zmq.Context) -> zmq.Socket:
        s = ctx.socket(zmq.DEALER)
        s.setsockopt(zmq.LINGER, 0)
        s.connect(self.endpoint)
        return s

    def run(self) -> None:
        ctx = zmq.Context()
        s = self._socket(ctx)
        try:
            if self.hello is not None:
                s.send(wire.encode(wire.Hello(self.sid, self.hello, claim=self.claim)))
                if not s.poll(self.timeout_ms) or not isinstance(wire.decode(s.recv()), wire.HelloAck):
                    self.problems.append("hello not acknowledged")
                    return
            seq = 0
            while not self.stop_flag.is_set():
                f = self.frames[seq % len(self.frames)]
                t = self.t_fn(seq)
                self.t_of[seq] = t
                body = wire.encode(wire.Frame(self.sid, seq, t, f))
                s.send(body)
                wait = self.reconnect_ms or self.timeout_ms
                deadline = time.monotonic() + self.timeout_ms / 1000
                while True:
                    if s.poll(wait):
                        m = wire.decode(s.recv(), 64 << 20)
                        if getattr(m, "seq", None) != seq:
                            continue  # a late answer to an earlier retry
                        self.answers[seq] = m
                        self.got_at[seq] = time.perf_counter()
                        break
                    if self.reconnect_ms is None or time.monotonic() > deadline:
                        self.problems.append(f"seq {seq}: no answer")
                        return
                    s.close(0)
                    s = self._socket(ctx)
                    if self.hello is not None:  # (the claim takes the stream over from the old socket)
                        s.send(wire.encode(wire.Hello(self.sid, self.hello, claim=self.claim)))
                    s.send(body)
                    self.retries += 1
                    self.retried.add(seq)
                seq += 1
        finally:
            s.close(0)
            ctx.term()

    def finish(self, timeout_s: float = 30.0) -> None:
        self.stop_flag.set()
        self.join(timeout_s)
        assert not self.is_alive(), f"{self.name} did not stop"
