"""band-13: the step cost of ``default``'s band_q with its rate gate (blend/withhlm.py, "Band q"):
one model file loaded twice, both with the shipped smoothing, A with band_q off (ones), B with
--band-q's fit and gate (bench/default_band_q.py), stepped alternately frame by frame
(``step_block``, the daemon's bundle path) in one process, n streams each, over a VALIDATION take
with the gaps protocol's bursts (seed 0; every stream its own state).  Per frame and stream: median
and p90 of each, and the median of the per-frame ratio B / A.

    OPENBLAS_NUM_THREADS=1 nice -n 19 .venv/bin/python bench/band13_stepcost.py /tmp/band13_train.npz \
        --band-q bench/results/band13_fit.json [--n 1 64] [--frames 1500] [--take walking_20] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from default_smooth_cost import step_ab  # noqa: E402  (bench/: the A/B loop)

from blend import withhlm  # noqa: E402
from lacuna.modelfile import load_model  # noqa: E402
from mocap import protocols, splits  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("model")
    ap.add_argument("--n", type=int, nargs="+", default=[1, 64])
    ap.add_argument("--frames", type=int, default=1500)
    ap.add_argument("--take", default="walking_20")
    ap.add_argument("--band-q", default="bench/results/band13_fit.json")
    ap.add_argument("--json")
    a = ap.parse_args()
    assert a.take in splits.VALIDATION
    m = splits.load_take(a.take)
    obs, _ = protocols.Gaps(seed=0, split="validation").occlusion(a.take, m.n_frames, m.channels, m.fps)
    F = np.where(obs, m.frames, np.nan)
    A, B = load_model(a.model), load_model(a.model)
    fit = json.loads(Path(a.band_q).read_text())
    for x in (A, B):
        x.set_smooth(**withhlm.SMOOTH)
    A.set_band_q(np.ones_like(np.array(fit["M"])))
    B.set_band_q(np.array(fit["M"]), fit["gate"])
    out: dict = {"model": a.model, "take": a.take, "machine": f"{platform.machine()} {platform.processor()}",
                 "load": list(__import__("os").getloadavg()), "cases": {}}
    for n in a.n:
        ta_, tb_ = step_ab(A, B, F, obs, n, a.frames)
        r = {"A_off_us": {"p50": float(np.median(ta_)), "p90": float(np.percentile(ta_, 90))},
             "B_band_q_us": {"p50": float(np.median(tb_)), "p90": float(np.percentile(tb_, 90))},
             "ratio_p50": float(np.median(tb_ / ta_)), "frames": int(len(ta_))}
        out["cases"][str(n)] = r
        print(f"n={n:3d}: off {r['A_off_us']['p50']:.1f} us/stream (p90 {r['A_off_us']['p90']:.1f}), band_q "
              f"{r['B_band_q_us']['p50']:.1f} (p90 {r['B_band_q_us']['p90']:.1f}); per-frame ratio median {r['ratio_p50']:.3f}",
              flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
