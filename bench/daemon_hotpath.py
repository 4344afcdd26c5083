"""CPU cost of the daemon's per-frame path without sockets: decode -> session -> batched step ->
fill message -> encode, through the real Daemon object (its transports replaced by a list).

Measured as process CPU time (not wall time) per frame, so that the other jobs on a shared
machine disturb it far less than round-trip latency; medians over repeats.

    .venv/bin/python bench/daemon_hotpath.py --repeats 7 --json bench/daemon_hotpath.json

Run with ``PYTHONPATH=DIR`` to measure another checkout's daemon with this same driver (A/B
across commits: ``PYTHONPATH=/tmp/perf-64e7005 python bench/daemon_hotpath.py ...``).

``--bundle`` adds rows where the 64 streams' frames of a tick come as one ``frames`` message.
``--behind K`` adds rows where each turn reads K bundles at once (a daemon behind its studio:
the first K - 1 are superseded by the newest and answered ``conflated``); CPU per frame is then
per frame served (each turn serves 64).  ``--gap-ms G`` sleeps G ms between ticks, as the live daemon waits between capture frames: the
caches and the CPU are then as cold as they are live (back to back, the figure is the warm
one).  ``--cpu-latency US`` holds a PM QoS request while measuring (daemon.cpu_latency_us).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from typing import Any

import msgpack
import numpy as np

from daemon import config, wire
from daemon.models import load_all
from daemon.pmqos import CpuLatency
from daemon.server import Daemon
from mocap.baselines import HoldModel, NearestNeighbourModel
from mocap.protocols import get_protocol

replies_of = getattr(wire, "replies_of", None)
WARM_TICKS = 20  # a filter's first frames cost more (the HLM's posterior starts over every phase)


def measure(d: Daemon, model: str, n_streams: int, ticks: int, frames: np.ndarray, channels: list[str],
            bundle: bool = False, gap_s: float = 0.0, behind: int = 1) -> tuple[float, float]:
    """(CPU, wall) microseconds per frame for ``ticks`` rounds of one frame on each of n streams,
    after WARM_TICKS rounds that are not timed; ``bundle``: each round is one ``frames`` message;
    ``gap_s``: a sleep between rounds.  CPU is process time over all rounds; wall is the median
    round's own duration (the sleeps excluded).  With sleeps, trust wall: the kernel charges CPU
    time by the scheduler tick, and a thread that wakes on a timer is running when ticks land."""
    out: list[bytes] = []
    held: list[dict] = []

    def send(o, m, publish=False):  # what Transports.send does: a bundle's answers are packed at the flush
        if len(o) == 3:
            held.append(wire.to_map(m))
        else:
            out.append(wire.encode(m))

    def serve():
        d._serve()
        if held:  # (a tree from before wire.replies_of encoded each answer and joined them)
            out.append(replies_of(held) if replies_of else wire.join_replies([msgpack.packb(m, use_bin_type=True)
                                                                              for m in held]))
            held.clear()
        out.clear()

    d._send = send  # type: ignore[method-assign]
    if hasattr(d, "_send_fills"):  # a bundle served as arrays hands its fills over as maps (daemon/tickblock.py)
        d._send_fills = lambda o, maps: held.extend(maps)  # type: ignore[method-assign]
    sids = [f"{model}-{n_streams}-{time.monotonic_ns()}-{i}" for i in range(n_streams)]
    for sid in sids:
        d._handle(wire.encode(wire.Hello(sid, channels, model)), ("router", [b"x"]), time.perf_counter())
    fr = [[wire.Frame(sid, k, k / 120, frames[k % len(frames)]) for sid in sids] for k in range(behind * (WARM_TICKS + ticks))]
    msgs = [[wire.encode(wire.Bundle(fs))] if bundle else [wire.encode(f) for f in fs] for fs in fr]
    if behind > 1:  # (each turn reads ``behind`` bundles in a row)
        msgs = [sum(msgs[k:k + behind], []) for k in range(0, len(msgs), behind)]
    for k in range(WARM_TICKS):
        for b in msgs[k]:
            d._handle(b, ("router", [b"x"]), time.perf_counter())
        serve()
    msgs = msgs[WARM_TICKS:]
    walls = np.empty(ticks)
    c0 = time.process_time()
    for k in range(ticks):
        w0 = time.perf_counter()
        for b in msgs[k]:
            d._handle(b, ("router", [b"x"]), time.perf_counter())
        serve()
        walls[k] = time.perf_counter() - w0
        if gap_s:
            time.sleep(gap_s)
    cpu = time.process_time() - c0
    for sid in sids:
        d.sessions.reset(sid)
    return 1e6 * cpu / (ticks * n_streams), 1e6 * float(np.median(walls)) / n_streams


def count_calls(d: Daemon, model: str, frames: np.ndarray, channels: list[str]) -> tuple[int, int]:
    """(Python calls, C calls) from receipt to the fill handed to the transport, for one frame of
    one stream (after 50 that warm it), the bench's send (encoding) included: ``sys.setprofile``."""
    d._send = lambda o, m, publish=False: wire.encode(m)  # type: ignore[method-assign]
    sid = f"calls-{model}-{time.monotonic_ns()}"
    d._handle(wire.encode(wire.Hello(sid, channels, model)), ("router", [b"x"]), time.perf_counter())
    msgs = [wire.encode(wire.Frame(sid, k, k / 120, frames[k % len(frames)])) for k in range(51)]
    for b in msgs[:50]:
        d._handle(b, ("router", [b"x"]), time.perf_counter())
        d._serve()
    n = {"call": 0, "c_call": 0}

    def prof(frame: Any, event: str, arg: Any) -> None:
        if event in n:
            n[event] += 1

    sys.setprofile(prof)
    try:
        d._handle(msgs[50], ("router", [b"x"]), time.perf_counter())
        d._serve()
    finally:
        sys.setprofile(None)
    d.sessions.reset(sid)
    return n["call"], n["c_call"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--frames", type=int, default=3000, help="frames per measurement")
    ap.add_argument("--model", action="append", default=[], metavar="NAME=FILE", help="extra model file (HLM, CRBM)")
    ap.add_argument("--models", default="floor,hold,nn", help="builtin set to measure")
    ap.add_argument("--bundle", action="store_true", help="also 64 streams sent as one frames message a tick")
    ap.add_argument("--gap-ms", type=float, default=0.0, help="sleep between ticks (default 0: back to back)")
    ap.add_argument("--behind", type=int, default=1, metavar="K",
                    help="with --bundle, also rows of K bundles read in each turn (a daemon behind)")
    ap.add_argument("--cpu-latency", type=int, default=None, metavar="US", help="hold a PM QoS request while measuring")
    ap.add_argument("--calls", action="store_true", help="only count the calls of one frame (pass-through, one stream)")
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args(argv)
    qos = CpuLatency()
    if args.cpu_latency is not None and not qos.request(args.cpu_latency):
        raise SystemExit(f"--cpu-latency: {qos.error}")
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
    if args.calls:
        py, c = count_calls(d, "floor", frames, ch)
        print(f"one pass-through frame, receipt to send: {py} Python calls, {c} C calls")
        return 0
    rows = []
    for model in args.models.split(",") + [s.split("=", 1)[0] for s in args.model]:
        cases = [(1, False, 1), (64, False, 1)] + ([(64, True, 1)] if args.bundle else []) + \
            ([(64, True, args.behind)] if args.bundle and args.behind > 1 else [])
        for n, bundle, behind in cases:
            ticks = max(2, args.frames // n) if model in ("floor", "hold") else max(10, 600 // n)
            if args.gap_ms:
                ticks = min(ticks, 200)  # each tick waits gap_ms
            got = [measure(d, model, n, ticks, frames, ch, bundle, args.gap_ms / 1000.0, behind)
                   for _ in range(args.repeats)]
            vals, walls = [g[0] for g in got], [g[1] for g in got]
            row = {"model": model, "streams": n, "bundle": bundle, "behind": behind, "gap_ms": args.gap_ms,
                   "cpu_latency_us": args.cpu_latency,
                   "cpu_us_per_frame_median": round(float(np.median(vals)), 1),
                   "cpu_us_per_frame_min": round(float(np.min(vals)), 1),
                   "wall_us_per_frame_median": round(float(np.median(walls)), 1), "repeats": args.repeats}
            rows.append(row)
            print(f"{model:>6} {n:>3} streams{' bundled' if bundle else ''}{f' {behind} a turn' if behind > 1 else ''}: "
                  f"{row['cpu_us_per_frame_median']} us CPU "
                  f"per frame (min {row['cpu_us_per_frame_min']}), wall {row['wall_us_per_frame_median']} us per frame",
                  file=sys.stderr, flush=True)
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump({"command": "python bench/daemon_hotpath.py " + " ".join(argv or sys.argv[1:]), "rows": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
