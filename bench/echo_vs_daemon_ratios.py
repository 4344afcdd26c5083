"""Per-repeat hlm/pass-through ratios of bench/echo_vs_daemon.py's one-stream runs (each ratio
paired within its repeat and tree), their median per run and pooled over the runs given, and the
CPU a frame (issue 19's check, bench/notebook/hlm9.md).

    .venv/bin/python bench/echo_vs_daemon_ratios.py bench/results/echo_vs_daemon_single_hlm9_[cdef].json
"""
from __future__ import annotations

import json
import statistics
import sys


def main(paths: list[str]) -> int:
    pooled: dict[str, dict[str, list[float]]] = {}
    for p in paths:
        d = json.load(open(p))
        runs = [r for r in d["runs"] if r["case"] == "single"]
        print(f"{p}: {d['at']}, load {[round(x, 2) for x in d['loadavg']]}, "
              f"{ {k: v['commit'][:7] for k, v in d['roots'].items()} }")
        for tree in d["roots"]:
            got: dict[str, list[float]] = {"p99": [], "p50": [], "cpu": []}
            for rep in range(d["repeats"]):
                g = {r["target"]: r for r in runs if r["repeat"] == rep}
                h, f = g[f"{tree}:hlm"], g[f"{tree}:floor"]
                got["p99"].append(h["p99_ms"] / f["p99_ms"])
                got["p50"].append(h["p50_ms"] / f["p50_ms"])
                got["cpu"].append(h["cpu_us_per_frame"])
            for k, v in got.items():
                pooled.setdefault(tree, {}).setdefault(k, []).extend(v)
            print(f"  {tree:>5}: hlm/floor p99 {[round(x, 2) for x in got['p99']]} median {statistics.median(got['p99']):.2f}"
                  f"; p50 {[round(x, 2) for x in got['p50']]} median {statistics.median(got['p50']):.2f}"
                  f"; hlm CPU {[round(x) for x in got['cpu']]} us/frame")
    print("pooled:")
    for tree, v in pooled.items():
        print(f"  {tree:>5}: {len(v['p99'])} repeats, hlm/floor p99 median {statistics.median(v['p99']):.3f} "
              f"(range {min(v['p99']):.2f}-{max(v['p99']):.2f}), p50 median {statistics.median(v['p50']):.3f}, "
              f"hlm CPU median {statistics.median(v['cpu']):.0f} us/frame")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
