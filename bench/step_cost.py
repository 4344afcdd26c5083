"""CPU cost of one batched Filler step, in-process, for the model files `lacuna bench` served.

    .venv/bin/python bench/step_cost.py MODEL.npz [MODEL.npz ...] [--steps 39] [--rounds 5]

CMU 07_01, channels 40..61 (the arms) missing every frame (``--all-observed``: none); one warm-up step, then ``--steps``
steps of 1 and of 64 streams; prints ms of process CPU per step and us per frame, the median
over ``--rounds`` rounds in which the models take turns (the order rotating), so that a change in
the machine's load falls on every model alike; and each model's ratio to the first one.  It puts
the round trips of docs/BENCHMARKS.md ## Daemon latency beside what the model itself costs.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from lacuna.modelfile import load_model  # noqa: E402
from mocap.datasets import load_trial  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("models", nargs="+")
    ap.add_argument("--steps", type=int, default=39)
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--all-observed", action="store_true",
                    help="nothing missing (default-hlm's shadow check then runs its windows and their twin)")
    args = ap.parse_args()
    f = load_trial("07_01").frames
    obs = np.ones(f.shape[1], bool)
    if not args.all_observed:
        obs[40:] = False
    models = {path: load_model(path) for path in args.models}
    times: dict[str, list[list[float]]] = {p: [] for p in models}
    for r in range(args.rounds):
        order = args.models[r % len(args.models):] + args.models[:r % len(args.models)]
        for path in order:
            m = models[path]
            row = []
            for n in (1, 64):
                st = [m.stream() for _ in range(n)]
                O = np.repeat(obs[None], n, 0)
                m.step_batch(st, np.repeat(f[:1], n, 0), O)  # warm-up: first-call allocations
                c0 = time.process_time()
                for t in range(1, args.steps + 1):
                    m.step_batch(st, np.repeat(f[t % len(f):t % len(f) + 1], n, 0), O)
                row.append((time.process_time() - c0) / args.steps)
            times[path].append(row)
    med = {p: np.median(np.array(v), axis=0) for p, v in times.items()}
    ref = med[args.models[0]]
    print(f"median over {args.rounds} round(s) of {args.steps} steps, order rotating\n")
    print(f"| model | 1 stream, ms per step | 64 streams, ms per batched step (us per frame) | / {Path(args.models[0]).stem} (1; 64) |\n"
          "|---|---|---|---|")
    for path in args.models:
        one, many = med[path]
        print(f"| {Path(path).stem} | {one * 1e3:.3f} | {many * 1e3:.3f} ({many / 64 * 1e6:.1f}) | "
              f"{one / ref[0]:.2f}; {many / ref[1]:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
