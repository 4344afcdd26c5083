"""The view's web server: the page, its files, and the feed as Server-Sent Events (stdlib only).

``GET /`` the page; ``GET /static/NAME`` its script and style (package data, never a CDN);
``GET /events`` the feed: ``event: meta`` (skeleton, streams, settings) whenever it changed,
then ``event: frame`` (a :meth:`view.feed.Feed.tick` update) at the feed's rate;
``GET /state.json`` the newest meta and update at once (for scripts).

One ticker thread makes each update once; every page's connection thread waits for the next one
and sends the newest, so a slow page skips updates instead of queueing them (newest wins), and a
page that reads nothing only blocks its own thread.
"""
from __future__ import annotations

import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any

from view.feed import Feed, dumps

KEEPALIVE_S = 5.0  # an SSE comment this often keeps proxies and the page's EventSource content
STATIC = {"index.html": "text/html; charset=utf-8", "view.js": "text/javascript; charset=utf-8",
          "view.css": "text/css; charset=utf-8"}


class Broadcast:
    """The newest update, numbered; readers wait for a number above the one they have.  Beside it
    the *snapshot*: every stream's newest entry and the newest stats, for a page that opens later
    (an update holds only the streams with a new frame that tick, and a stats-only tick a second
    after a take ends would otherwise leave a late page with no pose at all).  The snapshot is kept as
    the object and turned into JSON only when a page opens or a script asks (once per update), not on
    every tick."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.n = 0
        self.update: str = ""
        self._snap: Any = None        # the snapshot's object (its entries are never changed after publish)
        self._snap_json: tuple[int, str] = (-1, "")
        self.meta: str = "{}"
        self.meta_version = -1

    def publish(self, update: str | None, meta: tuple[int, str] | None, snapshot: Any = None) -> None:
        with self.cond:
            if meta is not None:
                self.meta_version, self.meta = meta
            if update is not None:
                self.update = update
                self._snap = snapshot
                self.n += 1
            self.cond.notify_all()

    def snapshot(self) -> str:
        """The snapshot as JSON ("" before any update; the update itself where none was given)."""
        with self.cond:
            if self._snap is None:
                return self.update
            if self._snap_json[0] != self.n:
                self._snap_json = (self.n, dumps(self._snap))
            return self._snap_json[1]

    def wait(self, have: int, timeout: float) -> tuple[int, str, int, str]:
        """(number, update, meta version, meta); a reader with nothing yet (``have`` < 0) gets the snapshot."""
        with self.cond:
            self.cond.wait_for(lambda: self.n > have, timeout)
            return self.n, (self.snapshot() if have < 0 else self.update), self.meta_version, self.meta


class ViewServer:
    """Serve ``feed`` on ``host:port`` (port 0: the kernel picks; see :attr:`url`)."""

    def __init__(self, feed: Feed, host: str = "127.0.0.1", port: int = 8765):
        self.feed = feed
        self.bc = Broadcast()
        self.stop_event = threading.Event()
        self.clients = 0
        self.updates = 0
        handler = type("Handler", (_Handler,), {"view": self})
        self.httpd = ThreadingHTTPServer((host, port), handler)
        self.httpd.daemon_threads = True
        self.host, self.port = self.httpd.server_address[:2]
        self._threads: list[threading.Thread] = []

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/"

    def start(self) -> ViewServer:
        for target, name in ((self.httpd.serve_forever, "view-http"), (self._tick_loop, "view-tick")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def _tick_loop(self) -> None:
        period = 1.0 / self.feed.rate
        next_t = time.monotonic()
        meta_sent = -1
        latest: dict[str, Any] = {}   # each stream's newest entry, for the snapshot
        stats: Any = None
        while not self.stop_event.is_set():
            next_t += period
            try:
                upd = self.feed.tick()
            except Exception as e:  # a bug must not freeze the page: say it there, keep ticking
                self.feed.fail(f"view: {type(e).__name__}: {e}")
                upd = None
            meta = None
            v = self.feed.meta_version
            if v != meta_sent:
                m = self.feed.meta()
                meta_sent = m["version"]
                meta = (meta_sent, dumps(m))
                known = {s["id"] for s in m["streams"]}
                for sid in [sid for sid in latest if sid not in known]:   # streams the view forgot
                    del latest[sid]
            snap = None
            if upd is not None:
                for d in upd["streams"]:
                    latest[d["id"]] = {**latest.get(d["id"], {}), **d}   # a frame without a pose keeps the last pose
                stats = upd.get("stats", stats)
                snap = {**upd, "streams": list(latest.values())}
                if stats is not None:
                    snap["stats"] = stats
            if upd is not None or meta is not None:
                self.bc.publish(None if upd is None else dumps(upd), meta, snap)
                self.updates += upd is not None
            delay = next_t - time.monotonic()
            if delay < 0:  # fell behind (a stalled machine): do not try to catch up
                next_t = time.monotonic()
                delay = 0
            self.stop_event.wait(delay)

    def stop(self) -> None:
        self.stop_event.set()
        with self.bc.cond:
            self.bc.cond.notify_all()
        self.httpd.shutdown()
        self.httpd.server_close()
        for t in self._threads:
            t.join(5)


class _Handler(BaseHTTPRequestHandler):
    view: ViewServer
    protocol_version = "HTTP/1.1"

    def log_message(self, format: str, *args: Any) -> None:  # no line per request on the terminal
        pass

    def do_GET(self) -> None:
        path = self.path.split("?", 1)[0]
        if path == "/":
            path = "/static/index.html"
        if path.startswith("/static/") and path[len("/static/"):] in STATIC:
            name = path[len("/static/"):]
            self._send(200, STATIC[name], resources.files("view").joinpath("static", name).read_bytes())
        elif path == "/events":
            self._events()
        elif path == "/state.json":
            bc = self.view.bc
            body = '{{"meta":{},"update":{}}}'.format(bc.meta, bc.snapshot() or "null")
            self._send(200, "application/json", body.encode())
        else:
            self._send(404, "text/plain; charset=utf-8", b"not found\n")

    def _send(self, code: int, ctype: str, body: bytes) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _events(self) -> None:
        v = self.view
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        self.close_connection = True
        have, meta_sent = -1, None
        v.clients += 1
        try:
            while not v.stop_event.is_set():
                n, upd, mv, meta = v.bc.wait(have, KEEPALIVE_S)
                out = []
                if mv != meta_sent:
                    out.append(f"event: meta\ndata: {meta}\n\n")
                    meta_sent = mv
                if n > have and upd:
                    out.append(f"event: frame\ndata: {upd}\n\n")
                have = n
                self.wfile.write(("".join(out) or ": keepalive\n\n").encode())
                self.wfile.flush()
        except (BrokenPipeError, ConnectionResetError):
            pass  # the page went away
        finally:
            v.clients -= 1
