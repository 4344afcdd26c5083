"""Drive a headless Chromium over the DevTools protocol on a pipe (stdlib only; for the view's
tests and benchmarks).

``chromium --remote-debugging-pipe`` reads DevTools commands on its file descriptor 3 and writes
answers and events on 4, each a JSON text ended by a NUL byte: no websocket, no driver package,
no browser download (the distribution's ``/usr/bin/chromium``).  One page is opened and attached
with a flat session; :meth:`Browser.evaluate` runs JavaScript in it, :meth:`Browser.screenshot`
saves a PNG.

The launch flags are those known to work on this kind of machine (a closed network: without the
background-networking flags Chromium keeps trying to reach Google's hosts).
"""
from __future__ import annotations

import base64
import ctypes
import json
import os
import shutil
import subprocess
import tempfile
import threading
import time
from typing import Any

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome")
COMMAND_TIMEOUT_S = 30.0
PR_CAPBSET_DROP, CAP_SYS_NICE = 24, 23  # <linux/prctl.h>, <linux/capability.h>
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-extensions", "--mute-audio", "--hide-scrollbars"]


class BrowserError(RuntimeError):
    pass


def find_chromium() -> str | None:
    exe = os.environ.get("LACUNA_CHROMIUM")
    if exe:
        return exe
    for n in CHROMIUM_NAMES:
        p = shutil.which(n)
        if p:
            return p
    return None


class Browser:
    """One headless Chromium with one page of ``width`` x ``height`` CSS pixels at ``scale``
    device pixels each (the screen's devicePixelRatio), its CPU priority lowered by ``nice``."""

    def __init__(self, executable: str | None = None, width: int = 1400, height: int = 900, nice: int = 0,
                 scale: float = 1.0):
        exe = executable or find_chromium()
        if not exe:
            raise BrowserError("no Chromium found (apt-get install chromium, or set LACUNA_CHROMIUM)")
        self.profile = tempfile.mkdtemp(prefix="lacuna-chromium-")
        to_child_r, self._to_child = os.pipe()
        self._from_child, from_child_w = os.pipe()

        def fds() -> None:  # runs in the child before exec: the protocol's fixed descriptors 3 and 4,
            # and nothing else of ours (sockets of the test process) leaks into the browser
            a, b = os.dup(to_child_r), os.dup(from_child_w)  # (dup2 onto itself would keep close-on-exec)
            os.dup2(a, 3)
            os.dup2(b, 4)
            os.closerange(5, os.sysconf("SC_OPEN_MAX"))
            if nice:
                os.nice(nice)
            # no right to raise its priority: as root Chromium would set its browser, GPU and
            # compositor threads to nice -8 (an ordinary user's browser cannot)
            ctypes.CDLL(None, use_errno=True).prctl(PR_CAPBSET_DROP, CAP_SYS_NICE, 0, 0, 0)

        self.log_path = os.path.join(self.profile, "chromium.log")
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen([exe, *FLAGS, f"--user-data-dir={self.profile}", "--remote-debugging-pipe",
                                      f"--window-size={width},{height}", "about:blank"],
                                     stdin=subprocess.DEVNULL, stdout=self._log, stderr=self._log,
                                     preexec_fn=fds, close_fds=False)
        os.close(to_child_r)
        os.close(from_child_w)
        self._next_id = 0
        self._lock = threading.Lock()
        self._answers: dict[int, dict] = {}
        self._cond = threading.Condition()
        self.events: list[dict] = []
        self._reader = threading.Thread(target=self._read, name="cdp-read", daemon=True)
        self._reader.start()
        self.session: str | None = None
        self.target = ""
        self._other = ""  # a second tab, in front of ours while the page is hidden
        try:
            target = self.target = self.call("Target.createTarget", {"url": "about:blank"},
                                             session=False)["targetId"]
            self.session = self.call("Target.attachToTarget", {"targetId": target, "flatten": True},
                                     session=False)["sessionId"]
            self.call("Page.enable")
            self.call("Runtime.enable")
            self.call("Emulation.setDeviceMetricsOverride",
                      {"width": width, "height": height, "deviceScaleFactor": scale, "mobile": False})
        except BaseException:
            self.close()
            raise

    def _read(self) -> None:
        buf = b""
        while True:
            try:
                chunk = os.read(self._from_child, 1 << 16)
            except OSError:
                chunk = b""
            if not chunk:
                with self._cond:
                    self._answers[-1] = {"error": {"message": "Chromium closed the pipe"}}
                    self._cond.notify_all()
                return
            buf += chunk
            while b"\0" in buf:
                raw, buf = buf.split(b"\0", 1)
                msg = json.loads(raw)
                with self._cond:
                    if "id" in msg:
                        self._answers[msg["id"]] = msg
                    else:
                        self.events.append(msg)
                    self._cond.notify_all()

    def call(self, method: str, params: dict | None = None, session: bool = True,
             timeout_s: float = COMMAND_TIMEOUT_S) -> dict:
        with self._lock:
            self._next_id += 1
            mid = self._next_id
            msg: dict[str, Any] = {"id": mid, "method": method, "params": params or {}}
            if session and self.session:
                msg["sessionId"] = self.session
            os.write(self._to_child, json.dumps(msg).encode() + b"\0")
        with self._cond:
            if not self._cond.wait_for(lambda: mid in self._answers or -1 in self._answers, timeout_s):
                raise BrowserError(f"{method}: no answer from Chromium within {timeout_s:g} s")
            ans = self._answers.pop(mid, None) or self._answers[-1]
        if "error" in ans:
            raise BrowserError(f"{method}: {ans['error'].get('message')} ({self.log_tail()})")
        return ans.get("result", {})

    def goto(self, url: str) -> None:
        self.call("Page.navigate", {"url": url})

    def evaluate(self, expression: str, timeout_s: float = COMMAND_TIMEOUT_S) -> Any:
        """The value of a JavaScript expression (promises awaited), as JSON."""
        r = self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True, "awaitPromise": True},
                      timeout_s=timeout_s)
        if "exceptionDetails" in r:
            d = r["exceptionDetails"]
            raise BrowserError(f"JavaScript error: {d.get('exception', {}).get('description') or d.get('text')}")
        return r.get("result", {}).get("value")

    def wait_for(self, expression: str, timeout_s: float = 30.0, poll_s: float = 0.05) -> Any:
        """Poll until ``expression`` is truthy; returns its value (BrowserError on timeout)."""
        deadline = time.monotonic() + timeout_s
        last: Any = None
        while time.monotonic() < deadline:
            try:
                last = self.evaluate(expression)
            except BrowserError as e:  # the page may not have loaded its script yet
                last = str(e)
            else:
                if last:
                    return last
            time.sleep(poll_s)
        raise BrowserError(f"timed out after {timeout_s:g} s waiting for {expression!r} (last: {str(last)[:200]})")

    def screenshot(self, path: str) -> str:
        data = self.call("Page.captureScreenshot", {"format": "png"})["data"]
        with open(path, "wb") as fh:
            fh.write(base64.b64decode(data))
        return path

    def hide(self) -> None:
        """Put another tab in front of the page, as a user switching tabs does: the page's
        ``document.hidden`` turns true and Chromium stops its animation frames."""
        if not self._other:
            self._other = self.call("Target.createTarget", {"url": "about:blank", "newWindow": False},
                                    session=False)["targetId"]
        self.call("Target.activateTarget", {"targetId": self._other}, session=False)

    def show(self) -> None:
        """Bring the page's tab to the front again."""
        self.call("Target.activateTarget", {"targetId": self.target}, session=False)

    def cpu_seconds(self) -> float:
        """User + system CPU seconds of Chromium and every process it started (Linux /proc)."""
        return sum(self.cpu_by_process().values())

    def cpu_by_process(self) -> dict[str, float]:
        """CPU seconds of Chromium's processes by kind: ``browser`` (the one started), and each
        child's ``--type`` (``renderer``: the page's script, layout and canvas raster;
        ``gpu-process``: compositing, in software here; ``utility``, ``zygote``...), summed over
        processes of one kind (Linux /proc)."""
        from clients.harness import cpu_seconds

        out: dict[str, float] = {}
        for pid in self._tree():
            kind = "browser" if pid == self.proc.pid else "other"
            try:
                with open(f"/proc/{pid}/cmdline", "rb") as fh:
                    for a in fh.read().replace(b"\0", b" ").split():  # (its children rewrite argv as one string)
                        if a.startswith(b"--type="):
                            kind = a[len(b"--type="):].decode(errors="replace")
                            break
            except OSError:
                continue
            out[kind] = out.get(kind, 0.0) + (cpu_seconds(pid) or 0.0)
        return out

    def _tree(self) -> list[int]:
        kids: dict[int, list[int]] = {}
        for d in os.listdir("/proc"):
            if d.isdigit():
                try:
                    with open(f"/proc/{d}/stat") as fh:
                        ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
                except (OSError, ValueError, IndexError):
                    continue
                kids.setdefault(ppid, []).append(int(d))
        out, todo = [], [self.proc.pid]
        while todo:
            pid = todo.pop()
            out.append(pid)
            todo += kids.get(pid, [])
        return out

    def console_errors(self) -> list[str]:
        with self._cond:
            return [json.dumps(e["params"])[:300] for e in self.events
                    if e.get("method") == "Runtime.exceptionThrown"]

    def log_tail(self, n: int = 5) -> str:
        try:
            with open(self.log_path, errors="replace") as fh:
                return " | ".join(fh.read().strip().splitlines()[-n:])
        except OSError:
            return "(no log)"

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                with self._lock:
                    os.write(self._to_child, json.dumps({"id": 0, "method": "Browser.close"}).encode() + b"\0")
                self.proc.wait(5)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(5)
        for fd in (self._to_child, self._from_child):
            try:
                os.close(fd)
            except OSError:
                pass
        self._log.close()
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
