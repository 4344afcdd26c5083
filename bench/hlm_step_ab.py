"""Per-frame step cost of two HLM configurations, each run by its own source tree, alternating.

Under a shared machine's load only ratios measured in one run mean anything: this runs rounds
of (A, B) child processes one after the other, each timing the daemon's path for one stream
(``step_batch`` of one stream: the one-call compiled step) and for a batch of 64 streams over
the frames of a take with the pan2009 erasure (the second half has everything but the legs
missing), and reports each round's medians and the median ratio B / A.

    .venv/bin/python bench/hlm_step_ab.py --a SRC_A MODEL_A --b SRC_B MODEL_B [--rounds 4]

SRC is a source tree (a checkout of some commit; ``git archive`` one into a directory) put first
on PYTHONPATH; MODEL an HLM model file that tree can load.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

import numpy as np

CHILD = r"""
import json, sys, time
import numpy as np
from lacuna.modelfile import load_model
from mocap.protocols import get_protocol
model = load_model(sys.argv[1])
frames_n = int(sys.argv[2])
case = get_protocol("pan2009").cases()[0]
frames = np.where(case.observed, case.truth, np.nan)
T = frames.shape[0]
out = {"info": model.info()}
for n in (1, 64):
    streams = [model.stream() for _ in range(n)]
    offs = np.arange(n) * 37
    steps = frames_n if n == 1 else max(frames_n // 16, 50)
    ts = []
    for k in range(steps + 200):
        t = k % T
        rows = (t + offs) % T
        t0 = time.perf_counter()
        model.step_batch(streams, frames[rows], case.observed[rows])
        if k >= 200:                          # the first frames warm the caches and compile
            ts.append((time.perf_counter() - t0) / n)
    out[str(n)] = float(np.median(ts) * 1e6)
print(json.dumps(out))
"""


def run(src: str, model: str, frames: int) -> dict:
    env = {**os.environ, "PYTHONPATH": src, "OPENBLAS_NUM_THREADS": "1"}
    r = subprocess.run([sys.executable, "-c", CHILD, model, str(frames)], env=env, capture_output=True, text=True,
                       cwd=src, check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--a", nargs=2, required=True, metavar=("SRC", "MODEL"))
    ap.add_argument("--b", nargs=2, required=True, metavar=("SRC", "MODEL"))
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    rounds = []
    for i in range(args.rounds):
        a = run(*args.a, args.frames)
        b = run(*args.b, args.frames)
        rounds.append({"a": a, "b": b})
        print(f"round {i}: 1 stream A {a['1']:.1f} us  B {b['1']:.1f} us ({b['1'] / a['1']:.3f});  "
              f"64 streams A {a['64']:.1f}  B {b['64']:.1f} us/stream ({b['64'] / a['64']:.3f})", flush=True)
    for n in ("1", "64"):
        r = np.median([x["b"][n] / x["a"][n] for x in rounds])
        print(f"median ratio B / A, {n} stream(s): {r:.3f}")
    print(f"A: {rounds[0]['a']['info']}\nB: {rounds[0]['b']['info']}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"a": args.a, "b": args.b, "rounds": rounds}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
