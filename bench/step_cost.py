"""CPU cost of one batched Filler step, in-process, for the model files `lacuna bench` served.

    .venv/bin/python bench/step_cost.py MODEL.npz [MODEL.npz ...] [--steps 39]

CMU 07_01, channels 40..61 (the arms) missing every frame; one warm-up step, then ``--steps``
steps of 1 and of 64 streams; prints ms of process CPU per step and us per frame.  It puts
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
    args = ap.parse_args()
    f = load_trial("07_01").frames
    obs = np.ones(f.shape[1], bool)
    obs[40:] = False
    print("| model | 1 stream, ms per step | 64 streams, ms per batched step (us per frame) |\n|---|---|---|")
    for path in args.models:
        m = load_model(path)
        row = []
        for n in (1, 64):
            st = [m.stream() for _ in range(n)]
            O = np.repeat(obs[None], n, 0)
            m.step_batch(st, np.repeat(f[:1], n, 0), O)  # warm-up: first-call allocations
            c0 = time.process_time()
            for t in range(1, args.steps + 1):
                m.step_batch(st, np.repeat(f[t % len(f):t % len(f) + 1], n, 0), O)
            row.append((time.process_time() - c0) / args.steps)
        print(f"| {Path(path).stem} | {row[0] * 1e3:.3f} | {row[1] * 1e3:.3f} ({row[1] / 64 * 1e6:.1f}) |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
