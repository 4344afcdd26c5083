"""Per-frame fill time of the CRBM filler: K = 30 Gibbs iterations, S = 1, 4, 16 chains, one
stream (``stream.step``) and 16 streams batched (``model.step_batch``), on the taylor2007 walk
with its right leg (7 channels) or upper body (36) missing.  Also the training time.

    .venv/bin/python bench/crbm_fill_speed.py [--model crbm.npz] [--out bench/results/crbm_fill_speed.json]

Timings are per frame of one stream (batched: total call time / streams), medians and
percentiles over every erased frame, repeated; the machine is shared, so compare within a run.

BLAS runs single-threaded here (OPENBLAS_NUM_THREADS=1 unless already set): the products are
tiny, and on a busy 2-core machine OpenBLAS threads made 16 batched streams 7-20x slower
(measured: 629-1978 us against 94 us per stream).  A serving process should do the same.
"""
from __future__ import annotations

import argparse
import json
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads OpenBLAS; see docstring
import platform
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from crbm.persist import load  # noqa: E402
from crbm.train import train_model  # noqa: E402
from mocap.protocols import get_protocol  # noqa: E402


def pct(x: list[float]) -> dict[str, float]:
    a = np.asarray(x) * 1e6
    return {"median_us": float(np.median(a)), "p90_us": float(np.percentile(a, 90)),
            "p99_us": float(np.percentile(a, 99)), "n": int(a.size)}


def time_single(model, case, repeats: int) -> list[float]:
    out = []
    given = np.where(case.observed, case.truth, np.nan)
    for _ in range(repeats):
        st = model.stream()
        for t in range(case.truth.shape[0]):
            t0 = time.perf_counter()
            st.step(given[t], case.observed[t])
            dt = time.perf_counter() - t0
            if not case.observed[t].all():
                out.append(dt)
    return out


def time_core(model, case, repeats: int) -> list[float]:
    """The CRBM's own work per frame (``core_step`` on encoded features), without the shared
    representation encode/decode of the seam."""
    out = []
    given = np.where(case.observed, case.truth, np.nan)
    for _ in range(repeats):
        st = model.stream()
        for t in range(case.truth.shape[0]):
            z, zobs = st.repr_state.encode(given[t][None], case.observed[t][None])
            t0 = time.perf_counter()
            o = model.core_step(st.core_state, z, zobs)
            dt = time.perf_counter() - t0
            done = st.repr_state.decode(o.z, given[t][None], case.observed[t][None])
            st.repr_state.commit(done)
            if not case.observed[t].all():
                out.append(dt)
    return out


def time_batched(model, case, n_streams: int, repeats: int) -> list[float]:
    out = []
    given = np.where(case.observed, case.truth, np.nan)
    for _ in range(repeats):
        states = [model.stream() for _ in range(n_streams)]
        for t in range(case.truth.shape[0]):
            fr = np.repeat(given[t][None], n_streams, 0)
            ob = np.repeat(case.observed[t][None], n_streams, 0)
            t0 = time.perf_counter()
            model.step_batch(states, fr, ob)
            dt = time.perf_counter() - t0
            if not case.observed[t].all():
                out.append(dt / n_streams)
    return out


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", help="a trained CRBM model file (default: train one, 2000 epochs)")
    ap.add_argument("--epochs", type=int, default=None)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out")
    a = ap.parse_args()
    proto = get_protocol("taylor2007")
    res: dict = {"machine": f"{platform.machine()} {platform.processor() or ''} {os.cpu_count()} cores, "
                            f"python {platform.python_version()}, numpy {np.__version__}",
                 "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS"), "load_average": os.getloadavg(), "fill": {}}
    if a.model:
        model = load(a.model)
    else:
        ts = proto.training_set()
        t0 = time.perf_counter()
        model = train_model(ts.sequences, ts.channels, epochs=a.epochs, progress=True, progress_every=500)
        res["train_seconds"] = time.perf_counter() - t0
        res["train_epochs"] = model.meta["training"]["epochs"]
        print(f"training: {res['train_seconds']:.1f} s for {res['train_epochs']} epochs", file=sys.stderr)
    cases = {c.erased: c for c in proto.cases() if c.test == "35_29"}
    model.set_iterations(30)
    for erased, case in cases.items():
        for S in (1, 4, 16):
            model.set_chains(S)
            rc = pct(time_core(model, case, a.repeats))
            r1 = pct(time_single(model, case, a.repeats))
            rb = pct(time_batched(model, case, 16, max(1, a.repeats // 2)))
            res["fill"][f"{erased} S={S}"] = {"core": rc, "single": r1, "batched16_per_stream": rb}
            print(f"{erased:10s} K=30 S={S:2d}: core median {rc['median_us']:.0f} us (p99 {rc['p99_us']:.0f}); "
                  f"single stream.step median {r1['median_us']:.0f} us (p99 {r1['p99_us']:.0f}); "
                  f"16 streams batched {rb['median_us']:.0f} us per stream (p99 {rb['p99_us']:.0f})", file=sys.stderr)
    model.set_chains(1)
    model.set_mode("mean-field")
    rc = pct(time_core(model, cases["right-leg"], a.repeats))
    r = pct(time_single(model, cases["right-leg"], a.repeats))
    res["fill"]["right-leg mean-field K=30"] = {"core": rc, "single": r}
    print(f"right-leg mean-field K=30: core median {rc['median_us']:.0f} us, single median {r['median_us']:.0f} us",
          file=sys.stderr)
    model.set_mode("gibbs")
    for k in (5, 10):
        model.set_iterations(k)
        rc = pct(time_core(model, cases["right-leg"], a.repeats))
        res["fill"][f"right-leg K={k} S=1 (degraded)"] = {"core": rc}
        print(f"right-leg K={k} S=1: core median {rc['median_us']:.0f} us", file=sys.stderr)
    if a.out:
        os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
        with open(a.out, "w") as fh:
            json.dump(res, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
