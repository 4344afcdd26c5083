"""Our faithful CRBM trained on the released code's own random numbers, against the model the
released code trained from the same seed (issue 17, part 4; crbm/replay.py).

Octave regenerates every number train.m + mixgaussiancrbm.m draw for SEED (``OCTAVE_STREAMS``:
no training, ~6.4 GB of float32 for 2000 epochs, written to --work); ours trains on them; both
models are compared parameter by parameter and filled by our filler (crbm.anchor.score, the
anchor's crbmfill.m experiment, 10 fills).  The released model comes from the anchor's train.m
run with that seed (/work/shared/anchors/taylor-octave, README).

    nice -n 5 .venv/bin/python bench/crbm_released_draws.py --seed 1 \\
        --released-model /work/scratch-octave/m150_seed1.mat --work /tmp/streams --out bench/results/crbm_released_draws_seed1.json
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from crbm import anchor, replay  # noqa: E402
from mocap import datasets  # noqa: E402
from mocap.protocols import get_protocol  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--released-model", required=True, help="the anchor's train.m output for that seed (.mat)")
    ap.add_argument("--work", required=True, help="directory for the regenerated streams (kept for reuse)")
    ap.add_argument("--epochs", type=int, default=2000)
    ap.add_argument("--hidden", type=int, default=150)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    prefix = work / f"streams_seed{a.seed}_e{a.epochs}_h{a.hidden}"
    if not Path(f"{prefix}.uniforms.f32").exists():
        (work / "streams.m").write_text(replay.OCTAVE_STREAMS)
        env = {**os.environ, "SEED": str(a.seed), "EPOCHS": str(a.epochs), "NUMHID": str(a.hidden),
               "DATA": str(datasets.data_dir(required=True)), "OUT": str(prefix)}
        t0 = time.perf_counter()
        subprocess.run(["octave", "--no-gui", "-q", "streams.m"], cwd=work, env=env, check=True)
        print(f"streams regenerated in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    data = anchor.anchor_data()

    def show(e: int, err: float) -> None:
        if e in (10, 50, 100) or e % 250 == 0:
            print(f"epoch {e}: error {err * 2500:.1f} (the released log's errsum units)", file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    ours = replay.train_on_streams(prefix, data["sequences"], progress=show)
    secs = time.perf_counter() - t0
    theirs = anchor.load_octave_model(a.released_model)
    params = {}
    for k in ("W_", "A_", "B_", "c_", "b_"):
        x, y = getattr(ours, k), getattr(theirs, k)
        params[k.rstrip("_")] = {"max_abs_diff": float(np.abs(x - y).max()), "max_abs_released": float(np.abs(y).max()),
                                 "corr": float(np.corrcoef(x.ravel(), y.ravel())[0, 1])}
    circ = get_protocol("taylor2007").train_variance()
    scores = {}
    for name, m in (("ours on the released draws", ours), ("released model", theirs)):
        sc = anchor.score(m, data, repeats=a.repeats, circular_var=circ)
        scores[name] = {f"{t} {g}": v for (t, g), v in sorted(sc.items())}
        print(f"{name}: " + ", ".join(f"{k} {v['plain_var']:.2f}" for k, v in scores[name].items()), flush=True)
    print(json.dumps(params, indent=1))
    if a.out:
        os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
        with open(a.out, "w") as fh:
            json.dump({"seed": a.seed, "epochs": a.epochs, "train_seconds": round(secs, 1),
                       "final_recon_error_per_frame": ours.recon_errors_[-1], "params": params, "scores": scores}, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
