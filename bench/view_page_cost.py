"""What the live page costs Chromium per setting, alternating in one run: the page before this
change (another checkout's ``view/``, one canvas per stream, drawn at every update, device
pixels uncapped) against the one-canvas page at 30 fps, at 60 fps, and on a 2x screen with
the device pixels capped at 1 (the default) and not.

    python bench/view_page_cost.py --old /tmp/old-view --streams 8 16 --rounds 2 --out bench/results/view_page_cost

``--old DIR``: a directory holding the older ``view`` package (``git archive main view | tar -x -C DIR``);
without it the old variants are skipped.  One ordinary daemon (hold model fitted on CMU 07_02),
N streams of CMU 07_01 at 120 Hz; per run, over the steady window: Chromium's CPU by process kind
(/proc: ``renderer`` the page's script and canvas raster, ``gpu-process`` compositing in software,
``browser``), the renderer main thread's busy share (DevTools), the page's animation frames,
drawn frames and updates a second, the view process's CPU, and the daemon's round trip.
Writes OUT.json and OUT.png.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile

import numpy as np
from view_fps import ROOT, run  # (bench/ is this script's directory)

from clients.configfile import free_port
from clients.harness import DaemonProcess
from mocap.baselines import HoldModel
from mocap.datasets import load_trial

# name: (view arguments, page query, screen scale, old checkout?)
VARIANTS = {
    "old": ((), "", 1.0, True),
    "new-30fps": ((), "", 1.0, False),
    "new-60fps": (("--fps", "60"), "", 1.0, False),
    "old-2x": ((), "", 2.0, True),
    "new-30fps-2x-dpr1": ((), "", 2.0, False),
    "new-30fps-2x-dpr2": ((), "?dpr=2", 2.0, False),
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--streams", type=int, nargs="+", default=[8, 16])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    ap.add_argument("--old", metavar="DIR", help="a directory holding the older view/ package")
    ap.add_argument("--out", default="bench/results/view_page_cost")
    a = ap.parse_args()
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    variants = [v for v in a.variants if a.old or not VARIANTS[v][3]]
    if a.old and not os.path.isfile(os.path.join(a.old, "view", "static", "view.js")):
        raise SystemExit(f"--old {a.old}: no view/static/view.js there")
    work = tempfile.mkdtemp(prefix="lacuna-pagecost-")
    train = load_trial("07_02")
    model = os.path.join(work, "hold.npz")
    HoldModel.fit([train.frames], train.channels).save(model)
    d = DaemonProcess({"hold": model}, workdir=os.path.join(work, "daemon"), daemon={"budget_ms": 4.0},
                      zmq={"pub": f"tcp://127.0.0.1:{free_port()}"}).start()
    rows = []
    try:
        for r in range(a.rounds):
            for n in a.streams:
                k = r % len(variants)
                for name in variants[k:] + variants[:k]:
                    vargs, query, scale, old = VARIANTS[name]
                    out = os.path.join(work, f"r{r}_{n}_{name}.json")
                    load = os.getloadavg()[0]
                    row, _ = run(d, list(train.channels), model, n, "page", a.seconds, out, None, 0, query,
                                 view_args=vargs, view_cwd=a.old if old else ROOT, scale=scale)
                    row.update(round=r, variant=name, load_before=load, load_after=os.getloadavg()[0])
                    rows.append(row)
                    by = row["chromium_window_cpu_percent"]
                    print(f"round {r} N={n} {name:18s}: chromium {sum(by.values()):.0f}% "
                          f"(renderer {by.get('renderer', 0):.0f}, gpu {by.get('gpu-process', 0):.0f}, browser "
                          f"{by.get('browser', 0):.0f}), main thread busy {row['renderer_task_percent']:.0f}%, "
                          f"{row['page_fps']:.1f} fps, {row['page_draws_per_s']:.1f} drawn/s, view {row['view_cpu_percent']:.1f}%, "
                          f"daemon p50/p99 {row['p50_ms']:.2f}/{row['p99_ms']:.2f} ms (load {load:.1f})", flush=True)
    finally:
        d.stop()
    summary: dict = {}
    for n in a.streams:
        for name in variants:
            rr = [x for x in rows if x["streams"] == n and x["variant"] == name]
            kinds = sorted({k for x in rr for k in x["chromium_window_cpu_percent"]})
            summary[f"{n}/{name}"] = {
                "chromium_cpu_percent": float(np.median([sum(x["chromium_window_cpu_percent"].values()) for x in rr])),
                "by_process": {k: float(np.median([x["chromium_window_cpu_percent"].get(k, 0.0) for x in rr])) for k in kinds},
                **{k: float(np.median([x[k] for x in rr])) for k in ("renderer_task_percent", "page_fps", "page_draws_per_s",
                                                                     "page_updates_per_s", "view_cpu_percent", "p50_ms", "p99_ms")}}
    res = {"take": "CMU 07_01 at 120 Hz a stream; hold model fitted on 07_02; Chromium nice 0, headless, software",
           "seconds": a.seconds, "rounds": a.rounds, "summary": summary, "rows": rows}
    os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
    with open(a.out + ".json", "w") as fh:
        json.dump(res, fh, indent=1)
    plot(a.out + ".png", summary, a.streams, variants)
    print(json.dumps(summary, indent=1))
    return 0


def plot(path: str, summary: dict, streams: list[int], variants: list[str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11, 4.5))
    w = 0.8 / len(streams)
    for i, n in enumerate(streams):
        bottom = np.zeros(len(variants))
        for j, kind in enumerate(("renderer", "gpu-process", "browser")):
            v = np.array([summary[f"{n}/{name}"]["by_process"].get(kind, 0.0) for name in variants])
            ax.bar(np.arange(len(variants)) + i * w, v, w, bottom=bottom, color=f"C{j}", alpha=1.0 - 0.35 * i,
                   label=f"{kind}, {n} streams")
            bottom += v
    ax.set_xticks(np.arange(len(variants)) + w * (len(streams) - 1) / 2, variants, fontsize=8)
    ax.set_ylabel("Chromium CPU, % of one core (median of rounds)")
    ax.legend(fontsize=7, ncol=2)
    ax.set_title("lacuna view's page in headless Chromium (software raster and compositing), by setting")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
