"""One HLM stream's step in process, warm or after a wait, wall time per frame over the pan2009
held-out walk with the left arm and the head missing (median, p90, p99):

- ``stream.step``: the representation's compiled encoder, the compiled filter and the decoder as
  three calls, with the Python around them;
- the compiled filter kernel alone (``hlm.fast._step_many``), inside the former;
- ``model.step_batch`` of one stream, the daemon's seam, which runs the whole step in one
  compiled call (``hlm.fast.step_slot``) on a second stream of the same walk.

The two whole steps alternate frame by frame (each after its own wait), so a busy spell of the
shared machine falls on both.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/hlm_step_cold.py bench/out/hlm.npz [--gap-ms 8] [--cpu-latency 0]

``--gap-ms`` sleeps between frames, as the daemon waits between capture frames; ``--cpu-latency``
holds a PM QoS request meanwhile (daemon.cpu_latency_us).
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

import hlm.fast as fast
from daemon.pmqos import CpuLatency
from lacuna.modelfile import load_model
from mocap.protocols import get_protocol

SKIP = 50  # first frames not counted (the filter's posterior starts over every phase)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model", help="an HLM model file")
    ap.add_argument("--gap-ms", type=float, default=0.0)
    ap.add_argument("--cpu-latency", type=int, default=None, metavar="US")
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args(argv)
    qos = CpuLatency()
    if args.cpu_latency is not None and not qos.request(args.cpu_latency):
        raise SystemExit(f"--cpu-latency: {qos.error}")
    if not fast.enabled():
        raise SystemExit("the compiled step is off (numba missing or LACUNA_NO_JIT=1): nothing to time")
    m = load_model(args.model)
    proto = get_protocol("pan2009")
    ch = list(proto.training_set().channels)
    frames = proto.cases()[0].truth.astype(np.float64)[:, [ch.index(c) for c in m.channels]]
    obs = np.ones(frames.shape, bool)
    obs[:, [c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "head") for c in m.channels]] = False
    kernel: list[float] = []
    orig = fast._step_many

    def timed(*a):  # the compiled call alone
        t0 = time.perf_counter()
        orig(*a)
        kernel.append(time.perf_counter() - t0)

    fast._step_many = timed
    slot_calls: list[int] = []
    orig_slot = fast.step_slot

    def counted(*a, **k):
        slot_calls.append(1)
        return orig_slot(*a, **k)

    fast.step_slot = counted
    st, st1 = m.stream(), m.stream()
    whole, one = [], []
    try:
        for k in range(len(frames)):
            given = np.where(obs[k], frames[k], np.nan)
            t0 = time.perf_counter()
            st.step(given, obs[k])
            whole.append(time.perf_counter() - t0)
            if args.gap_ms:
                time.sleep(args.gap_ms / 1000.0)
            g1, o1 = given[None], obs[k][None]
            t0 = time.perf_counter()
            m.step_batch([st1], g1, o1)
            one.append(time.perf_counter() - t0)
            if args.gap_ms:
                time.sleep(args.gap_ms / 1000.0)
    finally:
        fast._step_many = orig
        fast.step_slot = orig_slot
        qos.release()
    if len(kernel) != len(whole) or len(slot_calls) != len(one):
        raise SystemExit(f"this model's stream did not take the compiled steps ({len(kernel)} and {len(slot_calls)} "
                         f"of {len(whole)} frames)")

    def pct(v: list[float]) -> list[float]:
        return [round(1e6 * float(x), 1) for x in np.percentile(v[SKIP:], [50, 90, 99])]

    row = {"gap_ms": args.gap_ms, "cpu_latency_us": args.cpu_latency, "frames": len(whole) - SKIP,
           "stream_step_us_p50_p90_p99": pct(whole), "kernel_us_p50_p90_p99": pct(kernel),
           "one_call_step_us_p50_p90_p99": pct(one)}
    print(json.dumps(row))
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump({"command": "python bench/hlm_step_cold.py " + " ".join(argv or sys.argv[1:]), **row}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
