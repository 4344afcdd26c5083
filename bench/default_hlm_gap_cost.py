"""One stream's CPU per step on a real gaps-protocol stream (TEST take walking_28, seed 0: real gaps
and, between them, default-hlm's shadow windows), in-process, for the model files given.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/default_hlm_gap_cost.py HLM.npz DEFAULT.npz DH.npz

A warm-up pass over the take per model (compiled code loaded, regression caches filled), then 3
rounds in turn; prints the median us per step.  bench/step_cost.py's masks are fixed (the arms
missing: no shadow window opens; or nothing missing): this one mixes both as a live stream does.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from lacuna.modelfile import load_model  # noqa: E402
from mocap import protocols  # noqa: E402


def main() -> int:
    models = {p: load_model(p) for p in sys.argv[1:]}
    case = [c for c in protocols.Gaps(seed=0, split="test").cases() if c.test == "walking_28"][0]
    x, obs = case.truth, case.observed
    T = len(x)
    for m in models.values():
        warm = [m.stream()]
        for t in range(T):
            m.step_batch(warm, x[t:t + 1], obs[t:t + 1])
    res: dict[str, list[float]] = {p: [] for p in models}
    for _ in range(3):
        for p, m in models.items():
            st = [m.stream()]
            m.step_batch(st, x[:1], obs[:1])
            c0 = time.process_time()
            for t in range(1, T):
                m.step_batch(st, x[t:t + 1], obs[t:t + 1])
            res[p].append((time.process_time() - c0) / (T - 1))
    for p, v in res.items():
        print(f"{Path(p).stem}: {np.median(v) * 1e6:.1f} us per step (walking_28, gaps seed 0, {T} frames, "
              f"{(~obs).any(1).mean():.2f} of them with a gap)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
