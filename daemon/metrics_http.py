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

With a :class:`view.in_daemon.DaemonView` (``[metrics] view = true``) the same thread also
serves the live view: ``/view/`` the page and its files (package data), ``/view/events`` its
feed as Server-Sent Events.  At most ``MAX_VIEW_PAGES`` feeds are open (one more gets 503); a
feed connection has no deadline but a bounded backlog: a page that has not taken the last
``MAX_BACKLOG`` bytes is closed (counted ``view_dropped``; its EventSource reconnects).  The
thread runs the view's tick at its display rate (the selector's timeout), never the main loop.
"""
from __future__ import annotations

import selectors
import socket
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from importlib import resources
from typing import Any

from daemon.security import address_allowed

MAX_CONNECTIONS = 32
DEADLINE_S = 5.0  # accept -> answer sent
MAX_REQUEST = 8192  # bytes of request line + headers
TICK_S = 0.25  # how often deadlines are checked (the selector's timeout)
MAX_VIEW_PAGES = 4  # open /view/events feeds
MAX_BACKLOG = 1 << 18  # bytes a feed may have unsent before it is closed
FEED_SNDBUF = 1 << 16  # the kernel's send buffer of a feed connection
VIEW_FILES = {"index.html": "text/html; charset=utf-8", "view.js": "text/javascript; charset=utf-8",
              "view.css": "text/css; charset=utf-8"}


class _Conn:
    __slots__ = ("sock", "since", "inbuf", "out", "feed")

    def __init__(self, sock: socket.socket, now: float):
        self.sock, self.since, self.inbuf, self.out = sock, now, b"", b""
        self.feed = False  # an open /view/events stream


class MetricsHTTP:
    """``MetricsHTTP(host, port, text)`` binds and starts the thread; ``close()`` stops it."""

    def __init__(self, host: str, port: int, text: Callable[[], str], max_connections: int = MAX_CONNECTIONS,
                 deadline_s: float = DEADLINE_S, allow: list[Any] | None = None, view: Any = None):
        self.text = text
        self.view = view  # view.in_daemon.DaemonView or None
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
        if view is not None:
            self.counts.update(view_pages=0, view_dropped=0, view_refused=0)
        self.last_error: str | None = None
        self._stop = False
        self.thread = threading.Thread(target=self._run, name="metrics-http", daemon=True)
        self.thread.start()

    def info(self) -> dict[str, Any]:
        d: dict[str, Any] = {"open": len(self.conns), "max_connections": self.max_connections, **self.counts,
                             "last_error": self.last_error}
        if self.view is not None:
            d["view"] = self.view.info()
        return d

    # ---- the thread ---------------------------------------------------------------------------
    def _run(self) -> None:
        while not self._stop:
            try:
                wait = TICK_S if self.view is None or not self.view.watched else min(TICK_S, self.view.due_in(time.monotonic()))
                events = self.sel.select(wait)
                now = time.monotonic()
                for key, mask in events:
                    if key.data is None:
                        self._accept(now)
                    else:
                        self._io(key.data, mask)
                if self.view is not None:
                    pages = sum(c.feed for c in self.conns.values())
                    self.view.watch(pages)
                    if pages and self.view.due_in(now) <= 0:
                        self._view_tick(now)
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

    def _view_tick(self, now: float) -> None:
        chunk = self.view.tick(now)
        if not chunk:
            return
        for c in [c for c in self.conns.values() if c.feed]:
            if len(c.out) > MAX_BACKLOG:  # not reading: closed, the daemon holds no more for it
                self.counts["view_dropped"] += 1
                self._drop(c)
                continue
            was = bool(c.out)
            c.out += chunk
            if not was:
                self.sel.modify(c.sock, selectors.EVENT_READ | selectors.EVENT_WRITE, c)

    def _io(self, c: _Conn, mask: int) -> None:
        try:
            if c.feed:
                self._feed_io(c, mask)
                return
            if mask & selectors.EVENT_READ and not c.out:
                data = c.sock.recv(4096)
                if not data:
                    self._drop(c)
                    return
                c.inbuf += data
                if b"\r\n\r\n" in c.inbuf or b"\n\n" in c.inbuf:
                    self._answer(c)
                    if c.feed:  # an open view feed: written as its updates come (_feed_io)
                        return
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

    def _feed_io(self, c: _Conn, mask: int) -> None:
        if mask & selectors.EVENT_READ:
            if not c.sock.recv(4096):  # the page went away (anything it sends is ignored)
                self._drop(c)
                return
        if mask & selectors.EVENT_WRITE and c.out:
            n = c.sock.send(c.out)
            c.out = c.out[n:]
            if not c.out:
                self.sel.modify(c.sock, selectors.EVENT_READ, c)

    def _view_answer(self, c: _Conn, path: str, head_only: bool) -> bool:
        """Answer a /view request; False: not one."""
        if self.view is None or not (path == "/view" or path.startswith("/view/")):
            return False
        name = path[len("/view/"):] or "index.html"
        if path == "/view":  # the page's URLs are relative to /view/
            c.out = b"HTTP/1.0 301 Moved Permanently\r\nLocation: /view/\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
        elif name == "events" and not head_only:
            if sum(x.feed for x in self.conns.values()) >= MAX_VIEW_PAGES:
                self.counts["view_refused"] += 1
                c.out = self._head("503 Service Unavailable", "text/plain; charset=utf-8", 25) + b"too many view pages open\n"
            else:
                c.feed = True
                self.counts["view_pages"] += 1
                c.sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, FEED_SNDBUF)  # (no autotuned megabytes)
                c.out = (b"HTTP/1.0 200 OK\r\nContent-Type: text/event-stream\r\nCache-Control: no-store\r\n"
                         b"Connection: close\r\n\r\n" + self.view.hello_chunk())
        elif name.startswith("static/") and name[len("static/"):] in VIEW_FILES or name == "index.html":
            fname = name[len("static/"):] if name.startswith("static/") else name
            body = resources.files("view").joinpath("static", fname).read_bytes()
            c.out = self._head("200 OK", VIEW_FILES[fname], len(body)) + (b"" if head_only else body)
        else:
            c.out = self._head("404 Not Found", "text/plain; charset=utf-8", 10) + b"not found\n"
        c.inbuf = b""
        self.sel.modify(c.sock, selectors.EVENT_READ | selectors.EVENT_WRITE if c.feed else selectors.EVENT_WRITE, c)
        return True

    @staticmethod
    def _head(status: str, ctype: str, length: int) -> bytes:
        return (f"HTTP/1.0 {status}\r\nContent-Type: {ctype}\r\nContent-Length: {length}\r\n"
                f"Cache-Control: no-store\r\nConnection: close\r\n\r\n").encode()

    def _answer(self, c: _Conn) -> None:
        line = c.inbuf.split(b"\n", 1)[0].decode("latin-1").strip().split()
        if len(line) >= 2 and line[0] in ("GET", "HEAD") and self._view_answer(c, line[1].split("?")[0], line[0] == "HEAD"):
            return
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
        for c in list(self.conns.values()):  # (oldest first: the rest are younger)
            if c.feed:
                continue  # an open view feed has no deadline (its backlog is bounded instead)
            if now - c.since <= self.deadline_s:
                return
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
            if self.view is not None:
                self.view.close()
