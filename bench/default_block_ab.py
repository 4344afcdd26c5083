"""``default``'s bundle step two ways in one process, alternating frame by frame (issue 19;
bench/notebook/osc-5.md):

A (main 5b13b52's path for ``default``): ``Model.step_block``, the base class's: ``step_batch``'s n
  Fills (each with the blend's Fill and the HLM's inside it) stacked into (n, C) arrays;
B (now): ``WithHLMModel.step_block``: the compiled mixing writes the rows, the blend's step into
  scratch rows, the HLM's block step, no Fill per stream.

Then, for both, what daemon/tickblock.py does with them before the maps: float32 frames and std,
the style posteriors' bytes, the phases as floats.  Two sets of 64 streams of one model (each its
own states), 37 frames apart over CMU 35_08 with the left arm missing (the frames
bench/echo_vs_daemon.py sends); every frame's arrays and bytes are compared.  The model:
``default`` trained small on TRAIN takes 35_01/06 (tests/test_daemon_wire_block_hlm.py's), cached.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/default_block_ab.py [--frames 2000] [--n 64]
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np

from lacuna.filler import Model
from lacuna.modelfile import load_model
from mocap.datasets import load_trial

ARM = ("lhumerus", "lradius", "lwrist", "lhand")


def _model(cache: str):
    if not os.path.exists(cache):
        from blend.withhlm import train_model
        from mocap import protocols, splits

        takes = ["35_01", "35_06"]  # (TRAIN takes; as tests/test_daemon_wire_block_hlm.py trains it)
        ms = [splits.load_take(t) for t in takes]
        ts = protocols.TrainingSet([m.frames for m in ms], ms[0].channels, 120.0, takes, [splits.ACTIVITY[t] for t in takes])
        os.makedirs(os.path.dirname(cache), exist_ok=True)
        train_model(ts, restarts=1, n_iter=3, screen_iters=None, cycle_frames=140).save(cache)
    return load_model(cache)


def _wire(bf):
    n = len(bf.frame)
    st = bf.style
    a = np.ascontiguousarray(st if isinstance(st, np.ndarray) else np.array(st), dtype=np.float32).reshape(n, -1)
    ph = bf.phase.tolist() if isinstance(bf.phase, np.ndarray) else [np.nan if p is None else p for p in bf.phase]
    return (bf.frame.astype(np.float32), bf.std.astype(np.float32), bf.filled, [a[i].tobytes() for i in range(n)],
            np.array(ph, float).tobytes())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--model", default=os.path.join(tempfile.gettempdir(), "lacuna-default-block", "default-3501-3506.npz"))
    args = ap.parse_args(argv)
    model = _model(args.model)
    take = load_trial("35_08")
    x = take.frames
    obs = np.ones(x.shape, bool)
    obs[:, [c.split(".")[0] in ARM for c in take.channels]] = False
    T, n = x.shape[0], args.n
    sa, sb = [model.stream() for _ in range(n)], [model.stream() for _ in range(n)]
    offs = np.arange(n) * 37
    ta, tb = [], []
    for k in range(args.frames + 200):
        rows = (k + offs) % T
        f, o = np.where(obs[rows], x[rows], np.nan), obs[rows]
        for which in ((0, 1) if k % 2 else (1, 0)):  # (which goes first alternates)
            t0 = time.process_time_ns()
            got = _wire(Model.step_block(model, sa, f, o) if which == 0 else model.step_block(sb, f, o))
            dt = (time.process_time_ns() - t0) / n / 1e3
            if k >= 200:
                (ta if which == 0 else tb).append(dt)
            if which == 0:
                ra = got
            else:
                rb = got
        assert all(np.array_equal(p, q) for p, q in zip(ra[:3], rb[:3])) and ra[3] == rb[3] and ra[4] == rb[4], k
    a, b = float(np.median(ta)), float(np.median(tb))
    print(f"{n} streams, {args.frames} frames: A (step_batch stacked) {a:.2f} us/stream, B (default's step_block) "
          f"{b:.2f} us/stream, B/A {b / a:.3f}; means {np.mean(ta):.2f} / {np.mean(tb):.2f}; every frame's arrays and "
          f"bytes equal; load {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
