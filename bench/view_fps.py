"""The live view on the capture box itself: the page's own frame rate, and whether the daemon's
round trip stays unchanged within noise while the page is open, with the daemon's serving
threads ordinary and real-time (SCHED_RR, ``daemon.realtime_priority``), alternating in one run.

    python bench/view_fps.py --streams 8 16 --seconds 8 --rounds 3 --out bench/results/view_fps

Two daemons (real ``lacuna serve`` processes, the hold model fitted on CMU 07_02, PUB enabled):
``ordinary`` and ``rt`` (its serving thread and ZeroMQ's I/O threads SCHED_RR at ``--realtime``;
needs root or CAP_SYS_NICE); ``--settings ... rt-client`` adds runs against the rt daemon with the
load client SCHED_RR as well (``chrt -r``), to tell the daemon's delay from the client's.  Per round, stream count and setting, one client process per
condition (N streams at 120 Hz of CMU 07_01 with the gaps protocol's dropouts, as ``lacuna bench``
sends them; the round trips kept for the histograms): ``without`` nothing subscribed; ``view`` a
``lacuna view`` process subscribed to the PUB (its default nice 10); ``page`` that and its page in
headless Chromium at ``--browser-nice`` (0: an ordinary user's browser, which cannot raise its
priority) on the same cores.  Settings and conditions alternate in order across rounds.

"Unchanged within noise" (per N and setting): the median over the ``page`` rounds of the round
trip's p50, and of its p99, each lie within the spread (lowest to highest) of the ``without``
rounds of the same run.  During a ``page`` run the page's animation frames, drawn frames and
received updates are counted on the page's own clock over the steady part of the run, and the
CPU of the view process and of Chromium's processes by kind (/proc).  Writes OUT.json (rows,
summary, verdicts, histogram counts), OUT.png (p50/p99 by round, page fps) and OUT_hist.png
(round-trip histograms, page open vs nothing subscribed), and OUT_page.png (a screenshot).
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

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from clients.configfile import free_port  # noqa: E402
from clients.control import control  # noqa: E402
from clients.harness import DaemonProcess, cpu_seconds  # noqa: E402
from mocap.baselines import HoldModel  # noqa: E402
from mocap.datasets import load_trial, trial_path  # noqa: E402
from view.headless import Browser  # noqa: E402
from view.process import ViewProcess  # noqa: E402

# the daemon ordinary; the daemon real-time; that and the load client (the capture software's
# stand-in) real-time too, to tell the daemon's delay from the client's
SETTINGS = ("ordinary", "rt", "rt-client")
DEFAULT_SETTINGS = ("ordinary", "rt")
CONDITIONS = ("without", "view", "page")
SETTLE_S = 2.0  # the first part of a run (streams starting, the page catching up) is not counted
NOISE_RULE = ("page-open median p50 (and p99) within [min, max] of the nothing-subscribed rounds, same N and setting; "
              "'all' also needs the page-open median of frames dropped (overdue + conflated) <= the most of those rounds; "
              "'not_worse': the page-open medians of p50, p99 and drops each <= the most of those rounds (one-sided)")
HIST_EDGES = np.geomspace(0.1, 200.0, 81)  # ms
# one load run, in its own process (as `lacuna bench --connect` runs it), keeping every round trip
CLIENT = """
import json, sys, numpy as np
from clients.bench import bench_take, run_one
from clients.replay import write_json
endpoint, n, seconds, out, pid, prefix = sys.argv[1:7]
channels = json.loads(sys.argv[7])
frames, observed, _ = bench_take(channels)
row, rtt = run_one(endpoint, channels, frames, observed, streams=int(n), rate=120.0, seconds=float(seconds),
                   model=None, prefix=prefix, pid=int(pid), progress=False)
np.save(out + ".npy", rtt.astype(np.float32))
write_json(out, row)
"""
# the renderer main thread's busy time by kind (DevTools Performance.getMetrics, seconds)
METRICS = {"task": "TaskDuration", "script": "ScriptDuration", "layout": "LayoutDuration", "style": "RecalcStyleDuration"}


def renderer_metrics(b: Browser) -> dict[str, float]:
    got = {m["name"]: m["value"] for m in b.call("Performance.getMetrics")["metrics"]}
    return {k: float(got.get(name, 0.0)) for k, name in METRICS.items()}


def start_client(daemon: DaemonProcess, channels: list[str], n: int, seconds: float, out: str,
                 rt: int | None = None) -> subprocess.Popen:
    prefix = f"vb{int(time.time() * 1000) % 10**8}"
    return subprocess.Popen([*(["chrt", "-r", str(rt)] if rt else []), sys.executable, "-c", CLIENT, daemon.endpoint, str(n), str(seconds), out, str(daemon.pid),
                             prefix, json.dumps(channels)], cwd=ROOT, stdout=subprocess.DEVNULL)


def finish(p: subprocess.Popen, out: str) -> tuple[dict, np.ndarray]:
    if p.wait() != 0:
        raise RuntimeError(f"the load client exited with {p.returncode}")
    with open(out) as fh:
        return json.load(fh), np.load(out + ".npy")


def run(daemon: DaemonProcess, channels: list[str], model_file: str, n: int, cond: str, seconds: float, out: str,
        shot: str | None, browser_nice: int, page_query: str, view_args: tuple[str, ...] = (),
        view_cwd: str | None = None, scale: float = 1.0, client_rt: int | None = None) -> tuple[dict, np.ndarray]:
    """One run; ``view_args`` more arguments of ``lacuna view``, ``view_cwd`` a directory with
    another checkout's ``view`` package to run instead, ``scale`` the screen's devicePixelRatio,
    ``client_rt`` the load client's SCHED_RR priority (None: ordinary)."""
    if cond == "without":
        return finish(start_client(daemon, channels, n, seconds, out, client_rt), out)
    args = ["--connect", daemon.zmq_opts["pub"], "--skeleton-file", str(trial_path("07_01")), "--channels", model_file,
            *view_args]
    with ViewProcess(args, cwd=view_cwd) as view, contextlib.ExitStack() as stack:
        b = stack.enter_context(Browser(width=1400, height=300 + 290 * ((n + 1) // 2), nice=browser_nice,
                                        scale=scale)) if cond == "page" else None
        if b:
            b.goto(view.url + page_query)
            b.wait_for("window.lacunaView && lacunaView.state.connected", 30)
        cpu0, w0 = cpu_seconds(view.proc.pid), time.perf_counter()
        bcpu0 = b.cpu_by_process() if b else {}
        p = start_client(daemon, channels, n, seconds, out, client_rt)
        try:
            if b:
                probe = (f"(() => {{ const s = lacunaView.state; const ids = Object.keys(s.streams);"
                         f" return ids.length >= {n} && ids.every(i => s.streams[i].pose) }})()")
                b.wait_for(probe, 60)
                time.sleep(SETTLE_S)  # (pacing the measurement window, not waiting for an event)
                read = "[lacunaView.state.raf, performance.now(), lacunaView.state.updates, lacunaView.state.draws, lacunaView.state.drawMs]"
                b.call("Performance.enable")
                r0, m0, c0, t0 = b.evaluate(read), renderer_metrics(b), b.cpu_by_process(), time.perf_counter()
                time.sleep(max(1.0, seconds - SETTLE_S - 3.0))
                r1, m1, c1, t1 = b.evaluate(read), renderer_metrics(b), b.cpu_by_process(), time.perf_counter()
                if shot:
                    b.screenshot(shot)
        finally:
            row, rtt = finish(p, out)
        wall = time.perf_counter() - w0
        cpu1 = cpu_seconds(view.proc.pid)
        bcpu1 = b.cpu_by_process() if b else {}
    row["view_cpu_percent"] = None if cpu0 is None or cpu1 is None else 100.0 * (cpu1 - cpu0) / wall
    if b:
        dt = (r1[1] - r0[1]) / 1000.0
        row.update(page_fps=(r1[0] - r0[0]) / dt, page_updates_per_s=(r1[2] - r0[2]) / dt,
                   page_draws_per_s=(r1[3] - r0[3]) / dt, page_window_s=dt,
                   page_js_draw_percent=100.0 * (r1[4] - r0[4]) / 1000.0 / dt,
                   **{f"renderer_{k}_percent": 100.0 * (m1[k] - m0[k]) / dt for k in METRICS},
                   chromium_cpu_percent=100.0 * (sum(bcpu1.values()) - sum(bcpu0.values())) / wall,
                   chromium_window_cpu_percent={k: 100.0 * (c1.get(k, 0.0) - c0.get(k, 0.0)) / (t1 - t0) for k in c1})
    return row, rtt


def summarise(rows: list[dict], streams: list[int]) -> dict:
    summary: dict = {}
    for n in streams:
        for setting in SETTINGS:
            s: dict = {}
            for cond in CONDITIONS:
                rr = [x for x in rows if x["streams"] == n and x["setting"] == setting and x["condition"] == cond]
                if not rr:
                    continue
                s[cond] = {k: float(np.median([x[k] for x in rr])) for k in ("p50_ms", "p99_ms", "served", "sent", "cpu_percent")}
                s[cond].update(p50_runs=[x["p50_ms"] for x in rr], p99_runs=[x["p99_ms"] for x in rr],
                               dropped_runs=[x["dropped"] for x in rr],
                               overdue_runs=[x["drop_reasons"].get("overdue", 0) for x in rr],
                               conflated_runs=[x["drop_reasons"].get("conflated", 0) for x in rr])
                s[cond]["dropped"] = float(np.median(s[cond]["dropped_runs"]))
                if cond != "without":
                    s[cond]["view_cpu_percent"] = float(np.median([x["view_cpu_percent"] for x in rr]))
                    s[cond]["view_cpu_percent_per_stream"] = s[cond]["view_cpu_percent"] / n
                if cond == "page":
                    for k in ("page_fps", "page_draws_per_s", "page_updates_per_s", "chromium_cpu_percent",
                              "page_js_draw_percent", *[f"renderer_{m}_percent" for m in METRICS]):
                        s[cond][k] = float(np.median([x[k] for x in rr]))
                    s[cond]["page_fps_min"] = float(min(x["page_fps"] for x in rr))
                    s[cond]["page_draws_per_s_min"] = float(min(x["page_draws_per_s"] for x in rr))
                    kinds = sorted({k for x in rr for k in x["chromium_window_cpu_percent"]})
                    s[cond]["chromium_cpu_percent_by_process"] = {
                        k: float(np.median([x["chromium_window_cpu_percent"].get(k, 0.0) for x in rr])) for k in kinds}
            if "without" in s and "page" in s:
                w, p = s["without"], s["page"]
                ok = {q: min(w[f"{q}_runs"]) <= p[f"{q}_ms"] <= max(w[f"{q}_runs"]) for q in ("p50", "p99")}
                # (a round trip measured on fewer frames is no better: the drops must not rise either)
                ok["drops"] = p["dropped"] <= max(w["dropped_runs"])
                # (one-sided: the page open left the round trip no worse than the worst nothing-subscribed round)
                ok["not_worse"] = (p["p50_ms"] <= max(w["p50_runs"]) and p["p99_ms"] <= max(w["p99_runs"])
                                   and ok["drops"])
                s["unchanged_within_noise"] = {**ok, "both": ok["p50"] and ok["p99"],
                                               "all": ok["p50"] and ok["p99"] and ok["drops"],
                                               "page_over_without_p50": p["p50_ms"] / w["p50_ms"],
                                               "page_over_without_p99": p["p99_ms"] / w["p99_ms"]}
            if s:
                summary[f"{n}/{setting}"] = s
    return summary


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--streams", type=int, nargs="+", default=[8, 16])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--conditions", nargs="+", choices=CONDITIONS, default=["without", "page"])
    ap.add_argument("--settings", nargs="+", choices=SETTINGS, default=list(DEFAULT_SETTINGS))
    ap.add_argument("--realtime", type=int, default=10, metavar="PRIO", help="the rt daemon's SCHED_RR priority (default 10)")
    ap.add_argument("--browser-nice", type=int, default=0, help="Chromium's nice increment (default 0: an ordinary browser)")
    ap.add_argument("--page", default="", metavar="QUERY", help="the page's address query, e.g. '?fps=60' (default: the view's own)")
    ap.add_argument("--out", default="bench/results/view_fps")
    ap.add_argument("--resummarise", action="store_true", help="only recompute OUT.json's summary from its rows")
    a = ap.parse_args()
    if a.resummarise:
        with open(a.out + ".json") as fh:
            res = json.load(fh)
        res["summary"] = summarise(res["rows"], a.streams)
        res["noise_rule"] = NOISE_RULE
        with open(a.out + ".json", "w") as fh:
            json.dump(res, fh, indent=1)
        print(json.dumps({k: v.get("unchanged_within_noise") for k, v in res["summary"].items()}, indent=1))
        return 0
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    work = tempfile.mkdtemp(prefix="lacuna-viewbench-")
    train = load_trial("07_02")
    model = os.path.join(work, "hold.npz")
    HoldModel.fit([train.frames], train.channels).save(model)
    daemons: dict[str, DaemonProcess] = {}
    rows: list[dict] = []
    hists: dict[str, list[np.ndarray]] = {}
    try:
        for setting in sorted({"rt" if x == "rt-client" else x for x in a.settings}):
            extra = {"realtime_priority": a.realtime} if setting == "rt" else {}
            d = DaemonProcess({"hold": model}, workdir=os.path.join(work, setting), daemon={"budget_ms": 4.0, **extra},
                              zmq={"pub": f"tcp://127.0.0.1:{free_port()}"}).start()
            daemons[setting] = d
            rt = control(d.endpoint, "status").result.get("realtime") or {}
            if setting == "rt" and not rt.get("held"):
                raise SystemExit(f"the rt daemon did not get SCHED_RR: {rt.get('error')}")
            print(f"{setting} daemon: realtime {rt}", flush=True)
        channels = list(train.channels)
        for r in range(a.rounds):
            for n in a.streams:
                settings = a.settings if r % 2 == 0 else a.settings[::-1]
                for si, setting in enumerate(settings):
                    k = (r + si) % len(a.conditions)
                    for cond in a.conditions[k:] + a.conditions[:k]:  # each condition first in turn
                        out = os.path.join(work, f"r{r}_{n}_{setting}_{cond}.json")
                        shot = f"{a.out}_page.png" if (cond == "page" and n == max(a.streams) and r == 0) else None
                        load = os.getloadavg()[0]
                        row, rtt = run(daemons["rt" if setting == "rt-client" else setting], channels, model, n, cond,
                                       a.seconds, out, shot, a.browser_nice, a.page,
                                       client_rt=a.realtime if setting == "rt-client" else None)
                        row.update(round=r, setting=setting, condition=cond, load_before=load, load_after=os.getloadavg()[0])
                        rows.append(row)
                        hists.setdefault(f"{n}/{setting}/{cond}", []).append(rtt)
                        extra = ""
                        if cond == "page":
                            extra = (f", page {row['page_fps']:.1f} fps, {row['page_draws_per_s']:.1f} drawn/s, "
                                     f"{row['page_updates_per_s']:.0f} updates/s, chromium {row['chromium_cpu_percent']:.0f}% CPU")
                        if cond != "without":
                            extra += f", view {row['view_cpu_percent']:.1f}% CPU"
                        dr = row["drop_reasons"]
                        print(f"round {r} N={n} {setting:8s} {cond:7s}: p50 {row['p50_ms']:.3f} p99 {row['p99_ms']:.3f} ms, "
                              f"served {row['served']}/{row['sent']}, dropped overdue {dr.get('overdue', 0)} conflated "
                              f"{dr.get('conflated', 0)}{extra} (load {load:.1f})",
                              flush=True)
    finally:
        for d in daemons.values():
            d.stop()
    summary = summarise(rows, a.streams)
    counts = {k: np.histogram(np.concatenate(v), HIST_EDGES)[0].tolist() for k, v in hists.items()}
    res = {"take": "CMU 07_01 streamed at 120 Hz a stream (gaps-protocol dropouts); hold model fitted on 07_02",
           "seconds": a.seconds, "rounds": a.rounds, "browser_nice": a.browser_nice, "realtime_priority": a.realtime,
           "page_query": a.page, "ncpu": os.cpu_count(),
           "noise_rule": NOISE_RULE,
           "summary": summary, "hist_edges_ms": HIST_EDGES.tolist(), "hist_counts": counts, "rows": rows}
    os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
    with open(a.out + ".json", "w") as fh:
        json.dump(res, fh, indent=1)
    plot(a.out, rows, a.streams, a.settings, a.conditions, hists)
    print(json.dumps({k: v.get("unchanged_within_noise") for k, v in summary.items()}, indent=1))
    print(f"wrote {a.out}.json {a.out}.png {a.out}_hist.png {a.out}_page.png")
    return 0


def plot(out: str, rows: list[dict], streams: list[int], settings: list[str], conds: list[str],
         hists: dict[str, list[np.ndarray]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5), gridspec_kw={"width_ratios": [3, 1]})
    x = 0
    ticks = []
    for n in streams:
        for setting in settings:
            for j, cond in enumerate(conds):
                rr = [r for r in rows if r["streams"] == n and r["setting"] == setting and r["condition"] == cond]
                ax1.scatter([x] * len(rr), [r["p50_ms"] for r in rr], marker="o", color=f"C{j}",
                            label=f"p50, {cond}" if x < len(conds) else None)
                ax1.scatter([x] * len(rr), [r["p99_ms"] for r in rr], marker="^", color=f"C{j}",
                            label=f"p99, {cond}" if x < len(conds) else None)
                x += 1
            ticks.append((x - (len(conds) + 1) / 2, f"{n} streams\n{setting}"))
            x += 1
        rr = [r for r in rows if r["streams"] == n and r["condition"] == "page"]
        ax2.scatter([n] * len(rr), [r["page_draws_per_s"] for r in rr], color="C1", label="drawn/s" if n == streams[0] else None)
        ax2.scatter([n] * len(rr), [r["page_fps"] for r in rr], color="C2", marker="x",
                    label="animation frames/s" if n == streams[0] else None)
    ax1.set_xticks([t for t, _ in ticks], [s for _, s in ticks])
    ax1.set_ylabel("daemon round trip, ms (120 Hz a stream)")
    ax1.set_yscale("log")
    ax1.legend(fontsize=8)
    ax2.axhline(30, color="grey", ls="--", lw=1)
    ax2.set_xlabel("streams")
    ax2.set_ylabel("page frames/s")
    ax2.set_ylim(0, 70)
    ax2.legend(fontsize=8)
    fig.suptitle("lacuna view on the same cores: the daemon's round trip by round (ordinary vs SCHED_RR), page frame rate")
    fig.tight_layout()
    fig.savefig(out + ".png", dpi=110)
    plt.close(fig)
    fig, axes = plt.subplots(len(streams), len(settings), figsize=(5.5 * len(settings), 3.4 * len(streams)), squeeze=False)
    for i, n in enumerate(streams):
        for j, setting in enumerate(settings):
            ax = axes[i][j]
            for k, cond in enumerate(conds):
                v = hists.get(f"{n}/{setting}/{cond}")
                if v:
                    a = np.concatenate(v)
                    ax.hist(a, HIST_EDGES, histtype="step", color=f"C{k}", density=True,
                            label=f"{cond}: p50 {np.percentile(a, 50):.2f}, p99 {np.percentile(a, 99):.2f} ms")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_title(f"{n} streams, daemon {setting}", fontsize=10)
            ax.set_xlabel("round trip, ms (all rounds pooled)")
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out + "_hist.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
