"""Per-frame cost of the online HLM filter at 120 Hz with 4 styles (M = 280 states, 56 features).

Times, over repeated frames of CMU 07_01 with the pan2009 erasure (half the frames with the
upper body missing), the feature-space core step (predict + update + fill + extras) and the full
Filler-seam step (representation encode/decode included), single stream and batched, for the
faithful filler (kappa 0), the stream-cycle adaptation (kappa 3, kappa_global 3, width 8: the
``hlm`` default) and that plus a change of style (style_switch 1e-3).  Reports median, p90, p99.

    .venv/bin/python bench/hlm_step.py [--model M.npz] [--frames 2000]

Without --model it trains on the pan2009 training set first (about a minute).
"""
from __future__ import annotations

import os

# One BLAS thread: on this shared 2-core machine OpenBLAS's second thread spin-waits against the
# other jobs and makes the batched products several times slower.  Set before numpy loads.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys
import time

import numpy as np

from lacuna.modelfile import load_model
from mocap.protocols import get_protocol


def pct(ts: list[float]) -> str:
    a = np.asarray(ts) * 1e6
    return f"median {np.median(a):7.1f} us  p90 {np.percentile(a, 90):7.1f} us  p99 {np.percentile(a, 99):7.1f} us"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model")
    ap.add_argument("--frames", type=int, default=2000)
    args = ap.parse_args(argv)
    proto = get_protocol("pan2009")
    if args.model:
        model = load_model(args.model)
    else:
        from hlm.methods import train_model

        ts = proto.training_set()
        print("training on pan2009 ...", file=sys.stderr, flush=True)
        model = train_model(ts.sequences, ts.channels, ts.names, **proto.options)
    case = proto.cases()[0]
    frames = np.where(case.observed, case.truth, np.nan)
    T = frames.shape[0]
    idx = np.arange(args.frames) % T
    p = model.params
    print(f"model: C={p.n_styles} M={p.n_states} F={model.representation.n_features}; {args.frames} frames of {case.test}")
    for label, kappa, switch in (("faithful", 0.0, 0.0), ("stream-cycle", 3.0, 0.0), ("style-switch", 3.0, 1e-3)):
        m = model.with_options(kappa=kappa, kappa_global=kappa, width=8, style_switch=switch)
        # core step in feature space
        z_all, o_all = m.encode_recording(case.truth, case.observed)
        z_all = np.where(o_all, z_all, np.nan)
        st = m.core_init(1)
        ts_core = []
        for t in idx:
            t0 = time.perf_counter()
            m.core_step(st, z_all[t : t + 1], o_all[t : t + 1])
            ts_core.append(time.perf_counter() - t0)
        print(f"{label}: core step, 1 stream     {pct(ts_core)}")
        s = m.stream()
        ts_seam = []
        for t in idx:
            t0 = time.perf_counter()
            s.step(frames[t], case.observed[t])
            ts_seam.append(time.perf_counter() - t0)
        print(f"{label}: seam step, 1 stream     {pct(ts_seam)}")
        for n in (8, 32, 64):
            streams = [m.stream() for _ in range(n)]
            offs = np.arange(n) * 37
            tb = []
            for t in idx[: max(args.frames // n * 4, 50)]:
                rows = (t + offs) % T
                t0 = time.perf_counter()
                m.step_batch(streams, frames[rows], case.observed[rows])
                tb.append((time.perf_counter() - t0) / n)
            print(f"{label}: seam step_batch n={n:<3d} {pct(tb)} per stream")
            cs = m.core_init(n)
            tc = []
            for t in idx[: max(args.frames // n * 4, 50)]:
                rows = (t + offs) % T
                t0 = time.perf_counter()
                m.core_step(cs, z_all[rows], o_all[rows])
                tc.append((time.perf_counter() - t0) / n)
            print(f"{label}: core step  batch n={n:<3d} {pct(tc)} per stream")
    return 0


if __name__ == "__main__":
    sys.exit(main())
