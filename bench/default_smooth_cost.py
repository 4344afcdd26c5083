"""The step cost of ``default``'s pop limit (blend/withhlm.py, "Smooth"): one model file loaded
twice, A with the smoothing off, B with the shipped choice, stepped alternately frame by frame
(``step_block``, the daemon's bundle path) in one process, n streams each, over a VALIDATION take
with the gaps protocol's bursts (seed 0; every stream its own state).  Per frame and stream: median
and p90 of each, and the median of the per-frame ratio B / A.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/default_smooth_cost.py MODEL.npz [--n 1 64] [--frames 1500] \
        [--take walking_20] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from blend import withhlm  # noqa: E402
from lacuna.modelfile import load_model  # noqa: E402
from mocap import protocols, splits  # noqa: E402


def step_ab(A, B, F: np.ndarray, obs: np.ndarray, n: int, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Models A and B stepped alternately frame by frame (``step_block``, n streams each, at different
    places of the take, the order swapping every frame): each one's us per frame and stream, the first
    50 frames (compiling, warming) left out."""
    sa, sb = [A.stream() for _ in range(n)], [B.stream() for _ in range(n)]
    ta: list[float] = []
    tb: list[float] = []
    for t in range(min(frames, F.shape[0])):
        rows = [(t + 37 * i) % F.shape[0] for i in range(n)]   # streams at different places of the take
        f, o = np.ascontiguousarray(F[rows]), np.ascontiguousarray(obs[rows])
        for model, st, acc in ((A, sa, ta), (B, sb, tb)) if t % 2 == 0 else ((B, sb, tb), (A, sa, ta)):
            t0 = time.perf_counter_ns()
            model.step_block(st, f, o)
            acc.append((time.perf_counter_ns() - t0) / 1000.0 / n)
    return np.array(ta[50:]), np.array(tb[50:])


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("model")
    ap.add_argument("--n", type=int, nargs="+", default=[1, 64])
    ap.add_argument("--frames", type=int, default=1500)
    ap.add_argument("--take", default="walking_20")
    ap.add_argument("--json")
    a = ap.parse_args()
    assert a.take in splits.VALIDATION
    m = splits.load_take(a.take)
    obs, _ = protocols.Gaps(seed=0, split="validation").occlusion(a.take, m.n_frames, m.channels, m.fps)
    F = np.where(obs, m.frames, np.nan)
    A, B = load_model(a.model), load_model(a.model)
    A.set_smooth(**withhlm.NO_SMOOTH)
    B.set_smooth(knots=False, pop=withhlm.POP, pop_tau=withhlm.POP_TAU, pop_rel=withhlm.POP_REL)
    out: dict = {"model": a.model, "take": a.take, "machine": f"{platform.machine()} {platform.processor()}",
                 "load": list(__import__("os").getloadavg()), "cases": {}}
    for n in a.n:
        ta_, tb_ = step_ab(A, B, F, obs, n, a.frames)
        r = {"A_off_us": {"p50": float(np.median(ta_)), "p90": float(np.percentile(ta_, 90))},
             "B_pop_us": {"p50": float(np.median(tb_)), "p90": float(np.percentile(tb_, 90))},
             "ratio_p50": float(np.median(tb_ / ta_)), "frames": int(len(ta_))}
        out["cases"][str(n)] = r
        print(f"n={n:3d}: off {r['A_off_us']['p50']:.1f} us/stream (p90 {r['A_off_us']['p90']:.1f}), pop limit "
              f"{r['B_pop_us']['p50']:.1f} (p90 {r['B_pop_us']['p90']:.1f}); per-frame ratio median {r['ratio_p50']:.3f}",
              flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
