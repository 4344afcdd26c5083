"""The block path's model step and the arrays the replies are built from, two ways in one
process, alternating frame by frame (issue 19; bench/notebook/hlmrows-4.md):

A (integ 93161c1's daemon/tickblock.py): ``step_batch``'s n Fills, then stacked (frames, std,
  filled as float32 arrays), the style posteriors and phases read from each Fill's extras, the
  styles made the bytes the wire carries;
B (now): ``step_block``'s arrays (the HLM's one compiled call writes them), the styles' bytes
  from its (n, K) array, the phases from its (n,) array.

Two copies of one HLM (two state pools), 64 streams 37 frames apart over CMU 35_08 with the left
arm missing (the frames bench/echo_vs_daemon.py sends); every frame's bytes are compared.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/hlm_block_ab.py MODEL.npz [--frames 3000] [--n 64]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from lacuna.modelfile import load_model
from mocap.datasets import load_trial

ARM = ("lhumerus", "lradius", "lwrist", "lhand")


def path_a(model, streams, f, o):
    fills = model.step_batch(streams, f, o)
    frames = np.array([x.frame for x in fills], dtype=np.float32)
    std = np.array([x.std for x in fills], dtype=np.float32)
    filled = np.array([x.filled for x in fills], dtype=bool)
    exs = [x.extras for x in fills]
    a = np.array([ex.get("style") for ex in exs], dtype=np.float32).reshape(len(fills), -1)
    return frames, std, filled, [a[i].tobytes() for i in range(len(fills))], [ex.get("phase") for ex in exs]


def path_b(model, streams, f, o):
    bf = model.step_block(streams, f, o)
    a = np.ascontiguousarray(bf.style, dtype=np.float32)
    return (bf.frame.astype(np.float32), bf.std.astype(np.float32), bf.filled, [a[i].tobytes() for i in range(len(a))],
            bf.phase.tolist())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--n", type=int, default=64)
    args = ap.parse_args(argv)
    ma, mb = load_model(args.model), load_model(args.model)
    take = load_trial("35_08")
    x = take.frames
    obs = np.ones(x.shape, bool)
    obs[:, [c.split(".")[0] in ARM for c in take.channels]] = False
    T, n = x.shape[0], args.n
    sa, sb = [ma.stream() for _ in range(n)], [mb.stream() for _ in range(n)]
    offs = np.arange(n) * 37
    ta, tb = [], []
    for k in range(args.frames + 200):
        rows = (k + offs) % T
        f, o = np.where(obs[rows], x[rows], np.nan), obs[rows]
        first = k % 2  # (which goes first alternates)
        for which in ((0, 1) if first else (1, 0)):
            t0 = time.process_time_ns()
            got = path_a(ma, sa, f, o) if which == 0 else path_b(mb, sb, f, o)
            dt = (time.process_time_ns() - t0) / n / 1e3
            if k >= 200:
                (ta if which == 0 else tb).append(dt)
            if which == 0:
                ra = got
            else:
                rb = got
        assert all(np.array_equal(p, q) for p, q in zip(ra[:3], rb[:3])) and ra[3] == rb[3] and ra[4] == rb[4], k
    a, b = float(np.median(ta)), float(np.median(tb))
    print(f"{n} streams, {args.frames} frames: A (step_batch + stacking) {a:.2f} us/stream, "
          f"B (step_block) {b:.2f} us/stream, B/A {b / a:.3f}; means {np.mean(ta):.2f} / {np.mean(tb):.2f}; "
          f"every frame's arrays and bytes equal")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
