"""CPU cost of the daemon's per-frame path without sockets: decode -> session -> batched step ->
fill message -> encode, through the real Daemon object (its transports replaced by a list).

Measured as process CPU time (not wall time) per frame, so that the other jobs on a shared
machine disturb it far less than round-trip latency; medians over repeats.

    .venv/bin/python bench/daemon_hotpath.py --repeats 7 --json bench/daemon_hotpath.json
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time

import numpy as np

from daemon import config, wire
from daemon.models import load_all
from daemon.server import Daemon
from mocap.baselines import HoldModel, NearestNeighbourModel
from mocap.protocols import get_protocol


WARM_TICKS = 20  # a filter's first frames cost more (the HLM's posterior starts over every phase)


def measure(d: Daemon, model: str, n_streams: int, ticks: int, frames: np.ndarray, channels: list[str]) -> float:
    """CPU microseconds per frame for ``ticks`` rounds of one frame on each of n streams, after
    WARM_TICKS rounds that are not timed."""
    out: list[bytes] = []
    d._send = lambda o, m, publish=False: out.append(wire.encode(m))  # type: ignore[method-assign]
    sids = [f"{model}-{n_streams}-{time.monotonic_ns()}-{i}" for i in range(n_streams)]
    for sid in sids:
        d._handle(wire.encode(wire.Hello(sid, channels, model)), ("router", [b"x"]), time.perf_counter())
    msgs = [[wire.encode(wire.Frame(sid, k, k / 120, frames[k % len(frames)])) for sid in sids]
            for k in range(WARM_TICKS + ticks)]
    for k in range(WARM_TICKS):
        for b in msgs[k]:
            d._handle(b, ("router", [b"x"]), time.perf_counter())
        d._serve()
    msgs = msgs[WARM_TICKS:]
    c0 = time.process_time()
    for k in range(ticks):
        for b in msgs[k]:
            d._handle(b, ("router", [b"x"]), time.perf_counter())
        d._serve()
    cpu = time.process_time() - c0
    for sid in sids:
        d.sessions.reset(sid)
    return 1e6 * cpu / (ticks * n_streams)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--frames", type=int, default=3000, help="frames per measurement")
    ap.add_argument("--model", action="append", default=[], metavar="NAME=FILE", help="extra model file (HLM, CRBM)")
    ap.add_argument("--models", default="floor,hold,nn", help="builtin set to measure")
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args(argv)
    proto = get_protocol("pan2009")
    ts = proto.training_set()
    ch = list(ts.channels)
    frames = proto.cases()[0].truth.astype(np.float32)
    frames[:, [c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "head") for c in ch]] = np.nan
    tmp = tempfile.mkdtemp(prefix="lacuna-hot-")
    HoldModel.fit(ts.sequences, ch).save(f"{tmp}/hold.npz")
    NearestNeighbourModel.fit(ts.sequences, ch).save(f"{tmp}/nn.npz")
    models = {"floor": {"builtin": "passthrough"}, "hold": {"file": f"{tmp}/hold.npz"}, "nn": {"file": f"{tmp}/nn.npz"}}
    models.update({s.split("=", 1)[0]: {"file": s.split("=", 1)[1]} for s in args.model})
    cfg = config.from_dict({"daemon": {"budget_ms": 1000.0, "max_streams": 100000, "log_level": "warning"},
                            "models": models, "zmq": {"router": "tcp://127.0.0.1:*"}})
    d = Daemon(cfg)
    table, errors = load_all(cfg)
    assert not errors, errors
    d._install(table)
    rows = []
    for model in args.models.split(",") + [s.split("=", 1)[0] for s in args.model]:
        for n in (1, 64):
            ticks = max(2, args.frames // n) if model in ("floor", "hold") else max(10, 600 // n)
            vals = [measure(d, model, n, ticks, frames, ch) for _ in range(args.repeats)]
            row = {"model": model, "streams": n, "cpu_us_per_frame_median": round(float(np.median(vals)), 1),
                   "cpu_us_per_frame_min": round(float(np.min(vals)), 1), "repeats": args.repeats}
            rows.append(row)
            print(f"{model:>6} {n:>3} streams: {row['cpu_us_per_frame_median']} us CPU per frame (min {row['cpu_us_per_frame_min']})",
                  file=sys.stderr, flush=True)
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump({"command": "python bench/daemon_hotpath.py " + " ".join(argv or sys.argv[1:]), "rows": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
