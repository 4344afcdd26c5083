"""Where the HLM's batched step spends its time, per stream, at n streams (default 64).

The model is an HLM file (bench/echo_vs_daemon.py's cache holds one per commit); the frames are
CMU 35_08 with the left arm missing (bench/echo_vs_daemon.py's case), stream i at frame 37 i of
the take (``--spread``).  After 200 warm frames, medians over the next frames of:

- ``step_batch`` of the n streams (what the daemon calls);
- the parts of the path with three compiled calls (``step_arrays``: ``fastrepr.encode``,
  ``core_step`` -> ``hlm.fast.step``, ``fastrepr.finish``) and, inside ``core_step``, the filter
  kernel ``_step_many`` alone;
- the one-call path (``hlm.fast.step_rows``) and the Fills built from its arrays;
- the work: states, the prediction's support, the fill's live states, observed features.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/hlm_step_profile.py MODEL.npz [--streams 64] [--frames 400]
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys
import time
from collections.abc import Callable

import numpy as np

from hlm import fast, online
from hlm.streamcycle import LIVE_STATS
from lacuna.filler import Fill
from lacuna.modelfile import load_model
from mocap import fastrepr
from mocap.datasets import load_trial

MISSING = ("lhumerus", "lradius", "lwrist", "lhand")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("--streams", type=int, default=64)
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--spread", type=int, default=37, help="frames between streams (0: every stream on the same "
                    "frame, as bench/daemon_hotpath.py sends)")
    args = ap.parse_args(argv)
    model = load_model(args.model)
    n, K = args.streams, args.frames
    ch = model.channels
    take = load_trial("35_08")
    frames = take.frames[:, take.index(ch)].astype(np.float64)
    obs = np.broadcast_to(~np.array([c.split(".")[0] in MISSING for c in ch]), frames.shape).copy()
    given = np.where(obs, frames, np.nan)
    T = frames.shape[0]
    tab = model.tables
    C, M = tab.shape
    streams = [model.stream() for _ in range(n)]
    offs = np.arange(n) * args.spread
    k = [0]

    def batch() -> np.ndarray:
        k[0] += 1
        return (k[0] + offs) % T

    def timed(fn: Callable[[np.ndarray], object]) -> float:
        ts = []
        for _ in range(K):
            r = batch()
            t0 = time.perf_counter()
            fn(r)
            ts.append(time.perf_counter() - t0)
        return float(np.median(ts) / n * 1e6)

    for _ in range(200):
        r = batch()
        model.step_batch(streams, frames[r], obs[r])
    post = model.pool.core["post"][:n].reshape(n, -1)
    support = (post > 0).sum(1)
    live = (post > online.LIVE * post.max(1, keepdims=True)).sum(1)
    print(f"model: C={C} styles x M={M} states = {C * M}; F={model.representation.n_features} features, "
          f"{len(ch)} channels; {obs[0].sum()} channels observed")
    print(f"posterior support {int(np.median(support))} states (median; max {support.max()}), live states "
          f"{int(np.median(live))}")
    rows = {"step_batch (the daemon's call)": timed(lambda r: model.step_batch(streams, frames[r], obs[r]))}
    rs, cs = model._views(0, n)
    parts: dict[str, list[float]] = {"encode": [], "core_step": [], "finish": []}
    for _ in range(K):
        r = batch()
        t0 = time.perf_counter()
        z, zobs = fastrepr.encode(rs, given[r], obs[r])
        t1 = time.perf_counter()
        out = model.core_step(cs, z, zobs)
        t2 = time.perf_counter()
        fastrepr.finish(rs, out.z, out.z_std, given[r], obs[r])
        t3 = time.perf_counter()
        for key, dt in zip(parts, (t1 - t0, t2 - t1, t3 - t2)):
            parts[key].append(dt)
    for key, v in parts.items():
        rows[f"three calls: {key}"] = float(np.median(v) / n * 1e6)
    zz, zo = np.ascontiguousarray(z), np.ascontiguousarray(zobs)
    F = zz.shape[1]
    o1, s1, sty, ph = np.empty((n, F)), np.empty((n, F)), np.empty((n, C)), np.empty(n)
    first = np.zeros(n, bool)
    prow = np.arange(n, dtype=np.int64)
    rows["  the filter kernel _step_many alone"] = timed(lambda r: fast._step_many(
        post, first, tab.prior_flat, tab.d_pop, M, zz, zo, tab.em.fused_t, tab.mu, tab.bin0, tab.bin1, tab.bin_a,
        tab.kappa, tab.kappa_global, tab.n_bins, cs["D"], cs["W"], cs["G"], cs["GW"], prow, tab.lam_rows, tab.var_q,
        tab.pack, tab.cos, tab.sin, online.LIVE, LIVE_STATS, o1, s1, sty, ph, np.zeros((n, 4)), tab.ll_feats))
    tabs = fast.slot_tables(tab, model.representation)
    slots = np.array([s.slot for s in streams])
    rows["one call: hlm.fast.step_rows"] = timed(
        lambda r: fast.step_rows(tabs, model.pool, slots, frames[r], obs[r], online.LIVE, LIVE_STATS))
    done, std, ex = fast.step_rows(tabs, model.pool, slots, frames[:n], obs[:n], online.LIVE, LIVE_STATS)
    rows["one call: the Fills"] = timed(lambda r: [Fill(a, b, c, e) for a, b, c, e in zip(done, std, ~obs[r], ex)])
    for key, v in rows.items():
        print(f"{key:40s} {v:6.2f} us / stream")
    return 0


if __name__ == "__main__":
    sys.exit(main())
