"""Daemon round trip with ``default`` served beside HLM (and others), alternating in one run.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/default_latency.py default=D.npz hlm=H.npz [crbm=C.npz] \
        [--repeats 5] [--seconds 8] [--streams 1] [--prewarm MS ...] [--json bench/results/default_latency.json]

Each repeat runs ``lacuna bench --model FILE --streams N --rate 120 --seconds S`` (a fresh daemon
each time, the bench's own take and gaps-protocol dropouts) once per model, the order rotating
from repeat to repeat so that a change in the machine's load falls on every model alike.  Prints
the medians over repeats of p50 / p99 / the daemon's own p50, and each model's ratio to the first
model named after ``default`` (the target: one stream of default within 20% of hlm's round trip).
``--prewarm MS`` (repeatable) runs every model once per value of the daemon's ``prewarm_ms`` (rows
``NAME@pwMS``; without it the daemon's own default), the variants taking turns like the models.
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
    ap.add_argument("--prewarm", type=float, action="append", metavar="MS",
                    help="the daemon's prewarm_ms; repeat to run each model at each value")
    ap.add_argument("--json")
    args = ap.parse_args()
    given = dict(m.split("=", 1) for m in args.models)
    files: dict[str, str] = {}
    prewarm: dict[str, float | None] = {}
    for n, f in given.items():
        for pw in args.prewarm or [None]:
            v = n if pw is None else f"{n}@pw{pw:g}"
            files[v], prewarm[v] = f, pw
    names = list(files)
    runs: dict[str, list[dict]] = {n: [] for n in names}
    tmp = Path(tempfile.mkdtemp(prefix="default-latency-"))
    for r in range(args.repeats):
        order = names[r % len(names):] + names[:r % len(names)]
        for n in order:
            j = tmp / f"{n}-r{r}.json"
            cmd = ["bench", "--model", files[n], "--streams", str(args.streams), "--rate", f"{args.rate:g}",
                   "--seconds", f"{args.seconds:g}", "--json", str(j), "-q"]
            if prewarm[n] is not None:
                cmd += ["--prewarm", f"{prewarm[n]:g}"]
            print(f"[{r + 1}/{args.repeats}] lacuna {' '.join(cmd)}", file=sys.stderr, flush=True)
            if lacuna(cmd) != 0:
                raise SystemExit(f"bench run failed: {cmd}")
            runs[n].append(json.loads(j.read_text()))
    keys = ("p50_ms", "p99_ms", "daemon_proc_ms_p50", "daemon_proc_ms_p99")
    summ = {n: {k: float(np.median([x[k] for x in runs[n] if x.get(k) is not None])) for k in keys} for n in names}
    second = list(given)[1 if len(given) > 1 else 0]
    ref = {n: second if prewarm[n] is None else f"{second}@pw{prewarm[n]:g}" for n in names}   # same prewarm
    print(f"\n{args.streams} stream(s) x {args.rate:g} Hz, {args.seconds:g} s x {args.repeats} repeats, order rotating; "
          f"medians over repeats (ms)\n")
    print("| model | p50 | p99 | daemon p50 | daemon p99 | p50 / " + second + " | p99 / " + second + " |\n|---|---|---|---|---|---|---|")
    for n in names:
        s, r = summ[n], summ[ref[n]]
        print(f"| {n} | {s['p50_ms']:.3f} | {s['p99_ms']:.3f} | {s['daemon_proc_ms_p50']:.3f} | {s['daemon_proc_ms_p99']:.3f} | "
              f"{s['p50_ms'] / r['p50_ms']:.2f} | {s['p99_ms'] / r['p99_ms']:.2f} |")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"streams": args.streams, "rate": args.rate, "seconds": args.seconds,
                                               "repeats": args.repeats, "files": files, "prewarm_ms": prewarm, "median": summ,
                                               "runs": runs}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
