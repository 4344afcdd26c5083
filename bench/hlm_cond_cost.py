"""What the conditional fill (hlm.condfill) costs a step: one stream and a 64-stream batch, the
arms missing (a few missing features: the precision-matrix solve) or everything but the legs
(pan2009's pattern: the covariance solve), with it and without it, alternating rounds.

    .venv/bin/python bench/hlm_cond_cost.py MODEL.npz [--steps 300] [--rounds 5]

Process CPU per step (median of the rounds), us; a ratio measured in one run.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys
import time

import numpy as np

import hlm.methods  # noqa: F401  (registers the loader)
from lacuna.modelfile import load_model
from mocap import splits
from mocap.protocols import LEG_BONES, bone


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--take", default="35_30")
    args = ap.parse_args(argv)
    base = load_model(args.model)
    shrink = base.options.cond_shrink or 0.5
    models = {"with": base.with_options(cond_shrink=shrink), "without": base.with_options(cond_shrink=0.0)}
    m = splits.load_take(args.take)
    ch = m.channels
    arms = np.array([c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "lhand", "rhumerus", "rradius", "rwrist",
                                         "rhand") for c in ch])
    legs = np.array([bone(c) in LEG_BONES for c in ch])
    patterns = {"arms missing": ~arms, "all but legs": legs}
    T = min(args.steps, m.frames.shape[0])
    res: dict = {}
    for pat, keep in patterns.items():
        for n in (1, 64):
            for r in range(args.rounds):
                for name in (("with", "without") if r % 2 == 0 else ("without", "with")):
                    model = models[name]
                    streams = [model.stream() for _ in range(n)]
                    t0 = time.process_time()
                    for t in range(T):
                        f = np.where(keep, m.frames[t], np.nan)
                        if n == 1:
                            streams[0].step(f, keep)
                        else:
                            model.step_batch(streams, np.repeat(f[None], n, 0), np.repeat(keep[None], n, 0))
                    res.setdefault((pat, n, name), []).append((time.process_time() - t0) / T * 1e6)
    print("pattern | streams | with us/step | without us/step | ratio")
    for pat in patterns:
        for n in (1, 64):
            a, b = np.median(res[(pat, n, "with")]), np.median(res[(pat, n, "without")])
            print(f"{pat} | {n} | {a:.1f} | {b:.1f} | {a / b:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
