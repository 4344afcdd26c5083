"""Plot bench/archive_fill.py's results: takes/s of every run in time order, by configuration,
with each run's CPU share; writes a PNG beside the JSON (or --out).

    .venv/bin/python bench/archive_plot.py bench/results/archive_fill_run1.json bench/results/archive_fill.json \
        --out docs/archive_fill.png
"""
from __future__ import annotations

import argparse
import json


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", nargs="+")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = []
    for f in a.results:
        runs += json.load(open(f))["runs"]
    colors = {"local-1": "tab:blue", "local-2": "tab:cyan", "loopback-1": "tab:red", "loopback-2": "tab:orange"}
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    for i, r in enumerate(runs):
        c = colors.get(r["config"], "k")
        ax.bar(i, r["takes_per_s"], color=c, label=r["config"])
        ax2.bar(i, r.get("cpu_share") or 0, color=c)
        ax.text(i, r["takes_per_s"] + 0.02, f"{r['load1_before']:.0f}", ha="center", fontsize=7)
    h, lab = ax.get_legend_handles_labels()
    uniq = dict(zip(lab, h))
    ax.legend(uniq.values(), uniq.keys(), fontsize=8, ncol=4)
    ax.set_ylabel("takes / s (40 takes)")
    ax.set_title("lacuna fill, hlm-offline, 40 takes, runs in time order (number: load average)", fontsize=9)
    ax2.set_ylabel("CPU share per worker")
    ax2.set_xlabel("run")
    fig.tight_layout()
    fig.savefig(a.out, dpi=110)
    print(a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
