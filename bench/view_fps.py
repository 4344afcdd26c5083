"""The live view under load: the page's own frame rate, and the daemon's round trip with and
without the view subscribed (issue 20 target), alternating in one run.

    python bench/view_fps.py --streams 4 8 --seconds 10 --rounds 3 --out bench/results/view_fps

One daemon (a real ``lacuna serve``, the hold model fitted on CMU 07_02, PUB enabled).  Per
round and stream count, three ``lacuna bench --connect`` runs (real client processes, N streams
at 120 Hz of CMU 07_01 with the gaps protocol's dropouts, as ``lacuna bench`` sends them):
``without`` nothing else subscribed; ``view`` a ``lacuna view`` process subscribed to the PUB;
``page`` that and its page loaded in headless Chromium on the same machine (at ``nice`` 10, as
``lacuna view`` runs itself by default).  The order rotates
across rounds.  During a ``page`` run the page's requestAnimationFrame callbacks are counted over
the steady part of the run (all N streams drawn), with the page's own clock (performance.now),
and the CPU of the view process and of Chromium's process tree over the run.  Writes OUT.json,
OUT.png and a screenshot OUT_page.png of the page with the largest N.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from clients.configfile import free_port  # noqa: E402
from clients.harness import DaemonProcess, cpu_seconds  # noqa: E402
from mocap.baselines import HoldModel  # noqa: E402
from mocap.datasets import load_trial, trial_path  # noqa: E402
from view.headless import Browser  # noqa: E402
from view.process import ViewProcess  # noqa: E402

# nothing subscribed; a bare SUB that reads and drops everything (what any subscriber, `lacuna
# record` say, costs the daemon's PUB); lacuna view subscribed; and its page open
CONDITIONS = ("without", "sub", "view", "page")
BARE_SUB = """
import sys, zmq
s = zmq.Context().socket(zmq.SUB); s.setsockopt(zmq.SUBSCRIBE, b""); s.connect(sys.argv[1])
print("ready", flush=True)
while True:
    s.recv_multipart()
"""
SETTLE_S = 2.0
# Chromium on the capture box itself, started as `nice -n 10 chromium` (docs/CLIENTS.md) and, as an
# ordinary user's browser, unable to raise its priority again (--browser-nice 0: as root, unniced)
BROWSER_NICE = 10  # the first part of a bench run (streams starting, the page catching up) is not counted


# the renderer main thread's busy time by kind (DevTools Performance.getMetrics, seconds)
METRICS = {"task": "TaskDuration", "script": "ScriptDuration", "layout": "LayoutDuration", "style": "RecalcStyleDuration"}


def renderer_metrics(b: Browser) -> dict[str, float]:
    got = {m["name"]: m["value"] for m in b.call("Performance.getMetrics")["metrics"]}
    return {k: float(got.get(name, 0.0)) for k, name in METRICS.items()}


def bench_run(router: str, n: int, seconds: float, out: str, sub: str | None = None) -> dict:
    """One ``lacuna bench`` run; ``sub``: with a bare subscriber process on that PUB endpoint."""
    s = None
    if sub:
        s = subprocess.Popen([sys.executable, "-c", BARE_SUB, sub], stdout=subprocess.PIPE)
        assert s.stdout is not None
        s.stdout.readline()
    try:
        subprocess.run([sys.executable, "-m", "lacuna.cli", "bench", "--connect", router, "--streams", str(n),
                        "--rate", "120", "--seconds", str(seconds), "--json", out, "-q"],
                       check=True, stdout=subprocess.DEVNULL)
    finally:
        if s:
            s.kill()
            s.wait()
    with open(out) as fh:
        return json.load(fh)["runs"]["model"]


def with_view(daemon: DaemonProcess, model_file: str, n: int, seconds: float, out: str, page: bool,
              shot: str | None, browser_nice: int = 10) -> dict:
    """One bench run with ``lacuna view`` subscribed; ``page``: its page open in headless Chromium."""
    args = ["--connect", daemon.zmq_opts["pub"], "--skeleton-file", str(trial_path("07_01")),
            "--channels", model_file, "--rate", "30"]
    with ViewProcess(args) as view, contextlib.ExitStack() as stack:
        b = stack.enter_context(Browser(width=1400, height=300 + 290 * ((n + 1) // 2),
                                                      nice=browser_nice)) if page else None
        if b:
            b.goto(view.url)
            b.wait_for("window.lacunaView && lacunaView.state.connected", 30)
        cpu0, bcpu0 = cpu_seconds(view.proc.pid), b.cpu_seconds() if b else None
        w0 = time.perf_counter()
        p = subprocess.Popen([sys.executable, "-m", "lacuna.cli", "bench", "--connect", daemon.endpoint,
                              "--streams", str(n), "--rate", "120", "--seconds", str(seconds), "--json", out, "-q"],
                             stdout=subprocess.DEVNULL)
        try:
            if b:
                probe = (f"(() => {{ const s = lacunaView.state; const ids = Object.keys(s.streams);"
                         f" return ids.length >= {n} && ids.every(i => s.streams[i].pose) }})()")
                b.wait_for(probe, 60)
                time.sleep(SETTLE_S)
                read = ("[lacunaView.state.raf, performance.now(), lacunaView.state.updates, lacunaView.state.draws,"
                        " lacunaView.state.drawMs]")
                b.call("Performance.enable")
                r0, m0 = b.evaluate(read), renderer_metrics(b)
                time.sleep(max(1.0, seconds - SETTLE_S - 3.0))
                r1, m1 = b.evaluate(read), renderer_metrics(b)
                if shot:
                    b.screenshot(shot)
        finally:
            rc = p.wait()
        wall = time.perf_counter() - w0
        cpu1, bcpu1 = cpu_seconds(view.proc.pid), b.cpu_seconds() if b else None
        if rc != 0:
            raise RuntimeError(f"lacuna bench exited with {rc}")
    with open(out) as fh:
        row = json.load(fh)["runs"]["model"]
    row["view_cpu_percent"] = None if cpu0 is None or cpu1 is None else 100.0 * (cpu1 - cpu0) / wall
    if b:
        dt = (r1[1] - r0[1]) / 1000.0
        row.update(page_fps=(r1[0] - r0[0]) / dt, page_updates_per_s=(r1[2] - r0[2]) / dt,
                   page_draws_per_s=(r1[3] - r0[3]) / dt, page_window_s=dt,
                   page_js_draw_percent=100.0 * (r1[4] - r0[4]) / 1000.0 / dt,
                   **{f"renderer_{k}_percent": 100.0 * (m1[k] - m0[k]) / dt for k in METRICS},
                   chromium_cpu_percent=100.0 * (bcpu1 - bcpu0) / wall)
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--streams", type=int, nargs="+", default=[4, 8])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", default="bench/results/view_fps")
    ap.add_argument("--browser-nice", type=int, default=BROWSER_NICE,
                    help=f"Chromium's nice increment (default {BROWSER_NICE}); 0: Chromium as started by root")
    a = ap.parse_args()
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    work = tempfile.mkdtemp(prefix="lacuna-viewbench-")
    train = load_trial("07_02")
    model = os.path.join(work, "hold.npz")
    HoldModel.fit([train.frames], train.channels).save(model)
    daemon = DaemonProcess({"hold": model}, workdir=os.path.join(work, "daemon"), daemon={"budget_ms": 4.0},
                           zmq={"pub": f"tcp://127.0.0.1:{free_port()}"}).start()
    rows: list[dict] = []
    try:
        for r in range(a.rounds):
            for n in a.streams:
                order = CONDITIONS[r % 4:] + CONDITIONS[:r % 4]  # each condition first, middle, last in turn
                for cond in order:
                    out = os.path.join(work, f"r{r}_{n}_{cond}.json")
                    shot = f"{a.out}_page.png" if (cond == "page" and n == max(a.streams) and r == 0) else None
                    if cond in ("without", "sub"):
                        row = bench_run(daemon.endpoint, n, a.seconds, out, daemon.zmq_opts["pub"] if cond == "sub" else None)
                    else:
                        row = with_view(daemon, model, n, a.seconds, out, cond == "page", shot, a.browser_nice)
                    row.update(round=r, condition=cond)
                    rows.append(row)
                    fps = (f", page {row['page_fps']:.1f} fps ({row['page_updates_per_s']:.0f} updates/s), chromium "
                           f"{row['chromium_cpu_percent']:.0f}% CPU, renderer main thread busy {row['renderer_task_percent']:.0f}% "
                           f"(script {row['renderer_script_percent']:.0f}%, draw JS {row['page_js_draw_percent']:.0f}%)"
                           if cond == "page" else "")
                    if cond in ("view", "page"):
                        fps += f", view {row['view_cpu_percent']:.1f}% CPU"
                    print(f"round {r} N={n} {cond:7s}: p50 {row['p50_ms']:.3f} p99 {row['p99_ms']:.3f} ms, "
                          f"served {row['served']}/{row['sent']}{fps}", flush=True)
    finally:
        daemon.stop()
    summary = {}
    for n in a.streams:
        s: dict = {}
        for cond in CONDITIONS:
            rr = [x for x in rows if x["streams"] == n and x["condition"] == cond]
            s[cond] = {k: float(np.median([x[k] for x in rr]))
                       for k in ("p50_ms", "p90_ms", "p99_ms", "cpu_percent", "served", "sent")}
            if cond in ("view", "page"):
                s[cond]["view_cpu_percent"] = float(np.median([x["view_cpu_percent"] for x in rr]))
            if cond == "page":
                s[cond]["page_fps_min"] = float(min(x["page_fps"] for x in rr))
                s[cond]["page_fps_median"] = float(np.median([x["page_fps"] for x in rr]))
                for k in ["chromium_cpu_percent", "page_js_draw_percent", "page_updates_per_s"] + [f"renderer_{m}_percent" for m in METRICS]:
                    s[cond][k] = float(np.median([x[k] for x in rr]))
        summary[str(n)] = s
    res = {"take": "CMU 07_01 streamed by lacuna bench (gaps-protocol dropouts); hold model fitted on 07_02",
           "rate_hz": 120, "seconds": a.seconds, "browser_nice": a.browser_nice, "rounds": a.rounds, "view_rate": 30, "summary": summary, "rows": rows}
    os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
    with open(a.out + ".json", "w") as fh:
        json.dump(res, fh, indent=1)
    plot(a.out + ".png", rows, a.streams)
    print(json.dumps(summary, indent=1))
    print(f"wrote {a.out}.json {a.out}.png {a.out}_page.png")
    return 0


def plot(path: str, rows: list[dict], streams: list[int]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    for i, n in enumerate(streams):
        for j, cond in enumerate(CONDITIONS):
            rr = [x for x in rows if x["streams"] == n and x["condition"] == cond]
            x = i * 5 + j
            ax1.scatter([x] * len(rr), [r["p50_ms"] for r in rr], marker="o", color=f"C{j}",
                        label=f"p50, {cond}" if i == 0 else None)
            ax1.scatter([x] * len(rr), [r["p99_ms"] for r in rr], marker="^", color=f"C{j}",
                        label=f"p99, {cond}" if i == 0 else None)
        rr = [x for x in rows if x["streams"] == n and x["condition"] == "page"]
        ax2.scatter([n] * len(rr), [r["page_fps"] for r in rr], color="C1")
    ax1.set_xticks([i * 5 + 1.5 for i in range(len(streams))], [f"{n} streams" for n in streams])
    ax1.set_ylabel("daemon round trip, ms (lacuna bench, 120 Hz a stream)")
    ax1.set_yscale("log")
    ax1.legend(fontsize=8)
    ax2.axhline(30, color="grey", ls="--", lw=1)
    ax2.set_xlabel("streams")
    ax2.set_ylabel("page frames/s (requestAnimationFrame)")
    ax2.set_ylim(0, 70)
    fig.suptitle("lacuna view: page frame rate, and the daemon's round trip with and without the view")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    sys.exit(main())
