"""GET /metrics over HTTP: one thread, one selector, a bounded number of connections.

The daemon's Prometheus endpoint must never cost it more than a fixed amount, whatever the
scrapers (or anyone else who can reach the port) do: no thread per connection (a flood of
half-open connections once held 300 threads and, under systemd's ``TasksMax``, made the next
thread the daemon needed fail), a cap on open connections, a deadline per connection and a
cap on request bytes.

* One thread runs a ``selectors`` loop over the listening socket and every connection, all
  non-blocking.  It only reads the text the main loop publishes (``text()``: a str swap is
  atomic), never the live structures.
* At most ``MAX_CONNECTIONS`` are open; a new one beyond that closes the oldest (counted
  ``evicted``), so a real scraper still gets its answer during a flood of idle connections.
* A connection has ``DEADLINE_S`` from accept to having sent its answer; one that has not
  finished its request (headers end with an empty line, at most ``MAX_REQUEST`` bytes) by then
  is closed (counted ``timeouts``).  Each answer closes its connection (``Connection: close``).
* Every error inside the thread is caught and counted (``errors``); it never ends the thread.
"""
from __future__ import annotations

import selectors
import socket
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

from daemon.security import address_allowed

MAX_CONNECTIONS = 32
DEADLINE_S = 5.0  # accept -> answer sent
MAX_REQUEST = 8192  # bytes of request line + headers
TICK_S = 0.25  # how often deadlines are checked (the selector's timeout)


class _Conn:
    __slots__ = ("sock", "since", "inbuf", "out")

    def __init__(self, sock: socket.socket, now: float):
        self.sock, self.since, self.inbuf, self.out = sock, now, b"", b""


class MetricsHTTP:
    """``MetricsHTTP(host, port, text)`` binds and starts the thread; ``close()`` stops it."""

    def __init__(self, host: str, port: int, text: Callable[[], str], max_connections: int = MAX_CONNECTIONS,
                 deadline_s: float = DEADLINE_S, allow: list[Any] | None = None):
        self.text = text
        self.allow = allow  # source networks answered (metrics.allow; None: any, which config allows on loopback only)
        self.max_connections, self.deadline_s = max_connections, deadline_s
        fam = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.lsock = socket.socket(fam, socket.SOCK_STREAM)
        self.lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.lsock.bind((host, port))
        except OSError as e:
            self.lsock.close()
            raise OSError(f"metrics.http {host}:{port}: cannot bind ({e.strerror or e})") from None
        self.lsock.listen(64)
        self.lsock.setblocking(False)
        self.port = self.lsock.getsockname()[1]
        self.sel = selectors.DefaultSelector()
        self.sel.register(self.lsock, selectors.EVENT_READ, None)
        self.conns: OrderedDict[int, _Conn] = OrderedDict()  # fd -> connection, oldest first
        self.counts = {"served": 0, "evicted": 0, "timeouts": 0, "bad_requests": 0, "errors": 0, "denied": 0}
        self.last_error: str | None = None
        self._stop = False
        self.thread = threading.Thread(target=self._run, name="metrics-http", daemon=True)
        self.thread.start()

    def info(self) -> dict[str, Any]:
        return {"open": len(self.conns), "max_connections": self.max_connections, **self.counts,
                "last_error": self.last_error}

    # ---- the thread ---------------------------------------------------------------------------
    def _run(self) -> None:
        while not self._stop:
            try:
                events = self.sel.select(TICK_S)
                now = time.monotonic()
                for key, mask in events:
                    if key.data is None:
                        self._accept(now)
                    else:
                        self._io(key.data, mask)
                self._expire(now)
            except Exception as e:  # noqa: BLE001 - the endpoint must outlive any bug in it
                self.counts["errors"] += 1
                self.last_error = f"{type(e).__name__}: {e}"[:200]
                time.sleep(0.01)

    def _accept(self, now: float) -> None:
        for _ in range(64):
            try:
                s, addr = self.lsock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:  # EMFILE and the like: count, the listening socket stays
                self.counts["errors"] += 1
                self.last_error = f"accept: {e}"[:200]
                return
            if self.allow is not None and not address_allowed(addr[0], self.allow):
                self.counts["denied"] += 1  # closed unanswered
                s.close()
                continue
            s.setblocking(False)
            while len(self.conns) >= self.max_connections:
                _, old = self.conns.popitem(last=False)
                self._close(old, registered=True)
                self.counts["evicted"] += 1
            c = _Conn(s, now)
            self.conns[s.fileno()] = c
            self.sel.register(s, selectors.EVENT_READ, c)

    def _io(self, c: _Conn, mask: int) -> None:
        try:
            if mask & selectors.EVENT_READ and not c.out:
                data = c.sock.recv(4096)
                if not data:
                    self._drop(c)
                    return
                c.inbuf += data
                if b"\r\n\r\n" in c.inbuf or b"\n\n" in c.inbuf:
                    self._answer(c)
                elif len(c.inbuf) > MAX_REQUEST:
                    self.counts["bad_requests"] += 1
                    self._drop(c)
                    return
            if c.out:
                n = c.sock.send(c.out)
                c.out = c.out[n:]
                if not c.out:
                    self.counts["served"] += 1
                    self._drop(c)
        except (BlockingIOError, InterruptedError):
            pass
        except OSError:
            self._drop(c)

    def _answer(self, c: _Conn) -> None:
        line = c.inbuf.split(b"\n", 1)[0].decode("latin-1").strip().split()
        if len(line) < 2 or line[0] not in ("GET", "HEAD"):
            status, body = "405 Method Not Allowed", b"GET /metrics only\n"
        elif line[1].split("?")[0] not in ("/metrics", "/"):
            status, body = "404 Not Found", b"only /metrics here\n"
        else:
            status, body = "200 OK", self.text().encode()
        head = (f"HTTP/1.0 {status}\r\nContent-Type: text/plain; version=0.0.4; charset=utf-8\r\n"
                f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n").encode()
        c.out = head + (b"" if line and line[0] == "HEAD" else body)
        c.inbuf = b""
        self.sel.modify(c.sock, selectors.EVENT_WRITE, c)

    def _expire(self, now: float) -> None:
        while self.conns:
            c = next(iter(self.conns.values()))
            if now - c.since <= self.deadline_s:
                return  # (oldest first: the rest are younger)
            self.counts["timeouts"] += 1
            self._drop(c)

    def _drop(self, c: _Conn) -> None:
        self.conns.pop(c.sock.fileno(), None)
        self._close(c, registered=True)

    def _close(self, c: _Conn, registered: bool) -> None:
        try:
            if registered:
                self.sel.unregister(c.sock)
        except (KeyError, ValueError, OSError):
            pass
        try:
            c.sock.close()
        except OSError:
            pass

    def close(self) -> None:
        self._stop = True
        self.thread.join(2 * TICK_S + 1)
        for c in list(self.conns.values()):
            self._close(c, registered=True)
        self.conns.clear()
        try:
            self.sel.close()
        finally:
            self.lsock.close()
