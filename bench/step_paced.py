"""One stream's step paced like a capture system (wall time per step at a fixed rate), in process.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/step_paced.py A.npz B.npz ... [--rate 120] [--steps 600] \
        [--rounds 3] [--rehearse MS]

What the daemon sees of a model, without sockets: the frames of `lacuna bench` (CMU 07_01 with the
gaps protocol's dropouts, seed 0, clients.bench.bench_take) stepped one at a time, each one
``1 / rate`` after the last (sleeping in between, as the daemon does), wall time of each
``step_batch`` call; beside it the same frames back to back (warm).  ``--rehearse MS``: MS before
each paced step, a shadow stream steps the previous frame (what daemon/prewarm.py does).  Models
take turns round by round; prints the medians over rounds of each model's p50 / p99 (us) and
paced / warm.  It separates what a frame costs when the CPU's caches went cold between frames
from what the daemon adds around it.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from clients.bench import bench_take  # noqa: E402
from lacuna.modelfile import load_model  # noqa: E402


def run(m, F: np.ndarray, O: np.ndarray, steps: int, period: float | None, lead: float | None) -> np.ndarray:
    st, sh = [m.stream()], [m.stream()]
    m.step_batch(st, F[:1], O[:1])
    m.step_batch(sh, F[:1], O[:1])
    out = np.empty(steps)
    due = time.perf_counter()
    for t in range(1, steps + 1):
        i = t % len(F)
        if period is not None:
            due += period
            if lead is not None:
                _sleep_until(due - lead)
                j = (i - 1) % len(F)
                m.step_batch(sh, F[j:j + 1], O[j:j + 1])
            _sleep_until(due)
        t0 = time.perf_counter()
        m.step_batch(st, F[i:i + 1], O[i:i + 1])
        out[t - 1] = time.perf_counter() - t0
    return out * 1e6


def _sleep_until(t: float) -> None:
    d = t - time.perf_counter()
    if d > 0:
        time.sleep(d)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("models", nargs="+")
    ap.add_argument("--rate", type=float, default=120.0)
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--rehearse", type=float, metavar="MS")
    args = ap.parse_args()
    models = {p: load_model(p) for p in args.models}
    ch = list(models[args.models[0]].channels)
    frames, obs, src = bench_take(ch)
    F = np.where(obs, frames, np.nan).astype(np.float64)
    lead = None if args.rehearse is None else args.rehearse / 1000.0
    res: dict[str, list[list[float]]] = {p: [] for p in models}
    for r in range(args.rounds):
        order = args.models[r % len(args.models):] + args.models[:r % len(args.models)]
        for p in order:
            m = models[p]
            if list(m.channels) != ch:
                raise SystemExit(f"{p}: channels differ from {args.models[0]}'s")
            warm = run(m, F, obs, args.steps, None, None)
            paced = run(m, F, obs, args.steps, 1.0 / args.rate, lead)
            res[p].append([np.median(warm), np.percentile(warm, 99), np.median(paced), np.percentile(paced, 99)])
            print(f"[{r + 1}/{args.rounds}] {Path(p).stem}: warm p50 {res[p][-1][0]:.0f} us, paced p50 {res[p][-1][2]:.0f} us",
                  file=sys.stderr, flush=True)
    med = {p: np.median(np.array(v), 0) for p, v in res.items()}
    ref = med[args.models[0]]
    print(f"\n{src}, gaps seed 0, one stream; {args.steps} steps back to back (warm) and at {args.rate:g} Hz (paced"
          f"{'' if lead is None else f', rehearsed {args.rehearse:g} ms before'}); medians over {args.rounds} rounds, us\n")
    print(f"| model | warm p50 | warm p99 | paced p50 | paced p99 | paced / warm (p50) | paced p50 / {Path(args.models[0]).stem} |\n"
          "|---|---|---|---|---|---|---|")
    for p in args.models:
        w50, w99, p50, p99 = med[p]
        print(f"| {Path(p).stem} | {w50:.0f} | {w99:.0f} | {p50:.0f} | {p99:.0f} | {p50 / w50:.2f} | {p50 / ref[2]:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
