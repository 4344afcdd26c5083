"""What the view served by the daemon itself (``[metrics] view = true``) costs the daemon's round
trip: ``lacuna bench`` runs (N streams at 120 Hz of CMU 07_01, gaps-protocol dropouts) with no
page open, with a plain reader of its /view/events feed, and with its /view/ page open in
headless Chromium, the order rotating across rounds.

    python bench/view_daemon_cost.py --streams 8 16 --seconds 8 --rounds 3 --out bench/results/view_daemon_cost

Writes OUT.json; prints one line a run and the medians (the daemon's CPU, and its part for the
feed: ``feed`` minus ``none``, per stream).
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from clients.configfile import free_port  # noqa: E402
from clients.harness import DaemonProcess, cpu_seconds  # noqa: E402
from lacuna.cli import main as lacuna  # noqa: E402
from mocap.baselines import HoldModel  # noqa: E402
from mocap.datasets import load_trial, trial_path  # noqa: E402
from view.headless import Browser  # noqa: E402

# no page open (the view's SUB unsubscribed); a reader of the feed without a browser (the
# daemon's own cost of a page); the page open in headless Chromium on the same cores
MODES = ("none", "feed", "page")
TINY_HLM = ["--styles", "1", "--restarts", "1", "--iterations", "3", "-N", "120", "-q"]


class FeedReader(threading.Thread):
    """Reads /view/events and throws it away: the daemon's side of a page, without a browser."""

    def __init__(self, url: str):
        super().__init__(daemon=True)
        host, port = url[len("http://"):].split(":")
        self.sock = socket.create_connection((host, int(port)), timeout=30)
        self.sock.sendall(b"GET /view/events HTTP/1.0\r\n\r\n")
        self.bytes = 0
        self.start()

    def run(self) -> None:
        try:
            while True:
                b = self.sock.recv(65536)
                if not b:
                    return
                self.bytes += len(b)
        except OSError:
            return


def run(d: DaemonProcess, n: int, seconds: float, out: str, mode: str, nice: int) -> dict:
    page = mode == "page"
    b = Browser(width=1400, height=300 + 290 * ((n + 1) // 2), nice=nice) if page else None
    feed = FeedReader(d.http) if mode == "feed" else None
    try:
        if b:
            b.goto(d.http + "/view/")
            b.wait_for("window.lacunaView && lacunaView.state.connected", 30)
        c0, w0 = cpu_seconds(d.pid), time.perf_counter()
        p = subprocess.Popen([sys.executable, "-m", "lacuna.cli", "bench", "--connect", d.endpoint, "--streams", str(n),
                              "--rate", "120", "--seconds", str(seconds), "--json", out, "-q", "--model-name", "hold"],
                             stdout=subprocess.DEVNULL)
        fps = drawn = None
        if b:
            time.sleep(min(4.0, seconds / 2))
            read = "[lacunaView.state.raf, performance.now(), lacunaView.state.draws]"
            r0 = b.evaluate(read)
            time.sleep(max(1.0, seconds / 2 - 2.0))
            r1 = b.evaluate(read)
            dt = (r1[1] - r0[1]) / 1000.0
            fps, drawn = (r1[0] - r0[0]) / dt, (r1[2] - r0[2]) / dt
        if p.wait() != 0:
            raise RuntimeError("lacuna bench failed")
        cpu = 100.0 * (cpu_seconds(d.pid) - c0) / (time.perf_counter() - w0)
    finally:
        if b:
            b.close()
        if feed:
            feed.sock.close()
    with open(out) as fh:
        row = json.load(fh)["runs"]["model"]
    row.update(mode=mode, page_fps=fps, page_draws_per_s=drawn, daemon_cpu_percent=cpu, feed_bytes=feed.bytes if feed else None)
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--streams", type=int, nargs="+", default=[8])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--browser-nice", type=int, default=0)
    ap.add_argument("--out", default="bench/results/view_daemon_cost")
    a = ap.parse_args()
    work = tempfile.mkdtemp(prefix="lacuna-viewcost-")
    # the default model gives the page its skeleton (trained on 07_02); the streams are served by hold
    assert lacuna(["train", "hlm", str(trial_path("07_02")), "-o", os.path.join(work, "hlm.npz"), *TINY_HLM]) == 0
    train = load_trial("07_02")
    HoldModel.fit([train.frames], train.channels).save(os.path.join(work, "hold.npz"))
    http = free_port()
    d = DaemonProcess({"hlm": os.path.join(work, "hlm.npz"), "hold": os.path.join(work, "hold.npz")}, "hlm",
                      workdir=os.path.join(work, "d"), daemon={"budget_ms": 4.0}, zmq={"pub": f"tcp://127.0.0.1:{free_port()}"},
                      metrics={"http": f"127.0.0.1:{http}", "view": True})
    d.start()
    d.http = f"http://127.0.0.1:{http}"
    rows = []
    try:
        for r in range(a.rounds):
            for n in a.streams:
                for mode in MODES[r % 3:] + MODES[:r % 3]:
                    load = os.getloadavg()[0]
                    row = run(d, n, a.seconds, os.path.join(work, f"r{r}_{n}_{mode}.json"), mode, a.browser_nice)
                    row.update(round=r, load_before=load)
                    rows.append(row)
                    print(f"round {r} N={n} {mode:7s}: p50 {row['p50_ms']:.3f} p99 "
                          f"{row['p99_ms']:.3f} ms, served {row['served']}/{row['sent']}, daemon {row['daemon_cpu_percent']:.0f}% CPU"
                          + (f", page {row['page_fps']:.1f} fps, {row['page_draws_per_s']:.1f} drawn/s" if mode == "page" else "")
                          + (f", feed {row['feed_bytes'] / 1024:.0f} KiB" if mode == "feed" else "") + f" (load {load:.1f})",
                          flush=True)
    finally:
        d.stop()
    summary: dict = {}
    for n in a.streams:
        s = {k: {m: float(np.median([x[m] for x in rows if x["mode"] == k and x["streams"] == n]))
                 for m in ("p50_ms", "p99_ms", "daemon_cpu_percent", "served", "sent")} for k in MODES}
        s["page"]["page_fps_median"] = float(np.median([x["page_fps"] for x in rows if x["mode"] == "page" and x["streams"] == n]))
        s["page"]["page_draws_per_s_median"] = float(np.median([x["page_draws_per_s"] for x in rows
                                                                if x["mode"] == "page" and x["streams"] == n]))
        s["feed_cpu_percent_per_stream"] = (s["feed"]["daemon_cpu_percent"] - s["none"]["daemon_cpu_percent"]) / n
        summary[str(n)] = s
    os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
    with open(a.out + ".json", "w") as fh:
        json.dump({"take": "CMU 07_01 streamed by lacuna bench; hold model fitted on 07_02", "streams": a.streams,
                   "browser_nice": a.browser_nice, "summary": summary, "rows": rows}, fh, indent=1)
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
