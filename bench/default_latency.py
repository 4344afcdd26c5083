"""Daemon round trip with ``default`` served beside HLM (and others), alternating in one run.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/default_latency.py default=D.npz hlm=H.npz [crbm=C.npz] \
        [--repeats 5] [--seconds 8] [--streams 1] [--json bench/results/default_latency.json]

Each repeat runs ``lacuna bench --model FILE --streams N --rate 120 --seconds S`` (a fresh daemon
each time, the bench's own take and gaps-protocol dropouts) once per model, the order rotating
from repeat to repeat so that a change in the machine's load falls on every model alike.  Prints
the medians over repeats of p50 / p99 / the daemon's own p50, and each model's ratio to the first
model named after ``default`` (the target: one stream of default within 20% of hlm's round trip).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from lacuna.cli import main as lacuna  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("models", nargs="+", metavar="NAME=FILE")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--streams", type=int, default=1)
    ap.add_argument("--rate", type=float, default=120.0)
    ap.add_argument("--json")
    args = ap.parse_args()
    files = dict(m.split("=", 1) for m in args.models)
    names = list(files)
    runs: dict[str, list[dict]] = {n: [] for n in names}
    tmp = Path(tempfile.mkdtemp(prefix="default-latency-"))
    for r in range(args.repeats):
        order = names[r % len(names):] + names[:r % len(names)]
        for n in order:
            j = tmp / f"{n}-r{r}.json"
            cmd = ["bench", "--model", files[n], "--streams", str(args.streams), "--rate", f"{args.rate:g}",
                   "--seconds", f"{args.seconds:g}", "--json", str(j), "-q"]
            print(f"[{r + 1}/{args.repeats}] lacuna {' '.join(cmd)}", file=sys.stderr, flush=True)
            if lacuna(cmd) != 0:
                raise SystemExit(f"bench run failed: {cmd}")
            runs[n].append(json.loads(j.read_text()))
    keys = ("p50_ms", "p99_ms", "daemon_proc_ms_p50", "daemon_proc_ms_p99")
    summ = {n: {k: float(np.median([x[k] for x in runs[n] if x.get(k) is not None])) for k in keys} for n in names}
    ref = names[1] if len(names) > 1 else names[0]
    print(f"\n{args.streams} stream(s) x {args.rate:g} Hz, {args.seconds:g} s x {args.repeats} repeats, order rotating; "
          f"medians over repeats (ms)\n")
    print("| model | p50 | p99 | daemon p50 | daemon p99 | p50 / " + ref + " | p99 / " + ref + " |\n|---|---|---|---|---|---|---|")
    for n in names:
        s = summ[n]
        print(f"| {n} | {s['p50_ms']:.3f} | {s['p99_ms']:.3f} | {s['daemon_proc_ms_p50']:.3f} | {s['daemon_proc_ms_p99']:.3f} | "
              f"{s['p50_ms'] / summ[ref]['p50_ms']:.2f} | {s['p99_ms'] / summ[ref]['p99_ms']:.2f} |")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"streams": args.streams, "rate": args.rate, "seconds": args.seconds,
                                               "repeats": args.repeats, "files": files, "median": summ,
                                               "runs": runs}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
