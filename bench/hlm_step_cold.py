"""One HLM stream's step in process, warm or after a wait: the whole ``stream.step`` (the
representation and the Python around the filter) and the compiled filter kernel alone
(``hlm.fast._step_many``), wall time per frame, median over the pan2009 held-out walk with the
left arm and the head missing.

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
    st = m.stream()
    whole = []
    try:
        for k in range(len(frames)):
            t0 = time.perf_counter()
            st.step(np.where(obs[k], frames[k], np.nan), obs[k])
            whole.append(time.perf_counter() - t0)
            if args.gap_ms:
                time.sleep(args.gap_ms / 1000.0)
    finally:
        fast._step_many = orig
        qos.release()
    if len(kernel) != len(whole):
        raise SystemExit(f"this model's stream did not take the compiled step ({len(kernel)} of {len(whole)} frames)")
    row = {"gap_ms": args.gap_ms, "cpu_latency_us": args.cpu_latency, "frames": len(whole) - SKIP,
           "stream_step_us_p50": round(1e6 * float(np.median(whole[SKIP:])), 1),
           "kernel_us_p50": round(1e6 * float(np.median(kernel[SKIP:])), 1)}
    print(json.dumps(row))
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump({"command": "python bench/hlm_step_cold.py " + " ".join(argv or sys.argv[1:]), **row}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
