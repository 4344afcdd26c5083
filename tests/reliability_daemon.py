"""The reliability tests' tools around a real `lacuna serve` (clients.harness.DaemonProcess).

The daemon's stderr goes to a file (the fuzz test makes the daemon log ~10^5 rejections and the
test process needs its CPU for sending).  Ports are chosen up front (clients.configfile's
``loopback_config``, not ``:*``) so that a restarted daemon comes back on the same endpoints and
clients can reconnect to it.

Everything has a timeout; ``stop()`` kills what does not exit, so teardown never hangs.
"""
from __future__ import annotations

import os
import subprocess
import threading
import time
from typing import Any

import zmq

from clients import control as _control
from clients.configfile import free_port
from clients.configfile import loopback_config as write_config
from clients.harness import DaemonProcess
from clients.session import DaemonRefused
from daemon import wire

__all__ = ["Daemon", "DaemonProcess", "LockStep", "Sockets", "Supervisor", "control", "free_port", "recv_msg",
           "status", "udp_queue", "write_config"]

RECV_MS = 5000


def Daemon(config: str | os.PathLike[str], log_path: str | os.PathLike[str],  # noqa: N802 (reads as the class)
           env: dict[str, str] | None = None) -> DaemonProcess:
    """A daemon of ``config`` whose output goes to ``log_path``."""
    return DaemonProcess(config, env=env, log_path=log_path)


class Supervisor:
    """What systemd's Restart=on-failure does, as a thread: when the daemon dies with a failure
    status (or a signal), start it again after ``restart_s``.  ``restarts`` counts them."""

    def __init__(self, daemon: DaemonProcess, restart_s: float = 0.2):
        self.daemon = daemon
        self.restart_s = restart_s
        self.restarts = 0
        self.errors: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="supervisor", daemon=True)

    def start(self) -> Supervisor:
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
    """clients.control.request on a DEALER of the test's; the result map with ``_ok`` and ``_error``.
    A refused command (but ``reload``, whose refusal the tests read) raises RuntimeError."""
    try:
        m = _control.request(sock, cmd, stream, timeout_s=timeout_ms / 1000)
    except _control.DaemonUnavailable as e:
        raise TimeoutError(str(e)) from None
    except DaemonRefused as e:
        raise RuntimeError(f"{cmd} refused: {e}") from None
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
