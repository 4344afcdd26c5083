"""Where a bundled tick's time goes, phase by phase, in process (no sockets): decode the
``frames`` message, hand its frames to the sessions, plan and step them (scheduler), build the
fill messages, encode them.  Wall time of each phase (perf_counter), median over ticks after a
warm-up, ticks back to back (warm).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/daemon_phases.py --model hlm=bench/out/hlm.npz --json bench/results/daemon_phases.json

Rows for the pass-through filler and every ``--model``; 64 streams of the pan2009 held-out walk
with the left arm and the head missing.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import msgpack
import numpy as np

from daemon import config, wire
from daemon.models import load_all
from daemon.scheduler import fill_messages
from daemon.server import Daemon
from mocap.protocols import get_protocol

WARM_TICKS = 30
PHASES = ("decode", "sessions", "scheduler", "fill_messages", "encode")


def measure(d: Daemon, model: str, n: int, ticks: int, frames: np.ndarray, channels: list[str]) -> dict[str, float]:
    """Median microseconds per tick of each phase."""
    pack = msgpack.Packer(use_bin_type=True).pack
    sids = [f"{model}-{i}" for i in range(n)]
    for sid in sids:
        d.sessions.hello(wire.Hello(sid, channels, model))
    obs = np.isfinite(frames)
    msgs = [wire.encode(wire.Bundle([wire.Frame(s, k, k / 120, frames[k % len(frames)], obs[k % len(frames)])
                                     for s in sids])) for k in range(WARM_TICKS + ticks)]
    origin = ("router", [b"x"], "bundle")
    times: dict[str, list[float]] = {p: [] for p in PHASES}
    for k, b in enumerate(msgs):
        t0 = time.perf_counter()
        bundle = wire.decode(b, 1 << 22)
        t1 = time.perf_counter()
        for f in bundle.items:
            d.sessions.frame(f, origin, t0)  # type: ignore[arg-type]
        t2 = time.perf_counter()
        groups: dict = {}
        for s in d.sessions.sessions.values():
            if s.pending is not None:
                groups.setdefault((id(s.model), s.mapping.n_model), (s.model, []))[1].append(s)
        results = d.sched.run(groups, t2)
        t3 = time.perf_counter()
        replies = fill_messages(results, t3)
        t4 = time.perf_counter()
        for (s, _, _), m in zip(results, replies):
            s.last_seq, s.pending = s.pending.frame.seq, None  # type: ignore[union-attr]
            pack(wire.to_map(m))  # type: ignore[arg-type]
        t5 = time.perf_counter()
        if k >= WARM_TICKS:
            for p, a, z in zip(PHASES, (t0, t1, t2, t3, t4), (t1, t2, t3, t4, t5)):
                times[p].append((z - a) * 1e6)
    for sid in sids:
        d.sessions.reset(sid)
    return {p: float(np.median(v)) for p, v in times.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", action="append", default=[], metavar="NAME=FILE")
    ap.add_argument("--streams", type=int, default=64)
    ap.add_argument("--ticks", type=int, default=300)
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args(argv)
    proto = get_protocol("pan2009")
    ch = list(proto.training_set().channels)
    frames = proto.cases()[0].truth.astype(np.float32)
    frames[:, [c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "head") for c in ch]] = np.nan
    models = {"floor": {"builtin": "passthrough"}, **{s.split("=", 1)[0]: {"file": s.split("=", 1)[1]} for s in args.model}}
    cfg = config.from_dict({"daemon": {"budget_ms": 1000.0, "max_streams": 100000, "log_level": "warning"},
                            "models": models, "zmq": {"router": "tcp://127.0.0.1:*"}})
    d = Daemon(cfg)
    table, errors = load_all(cfg)
    assert not errors, errors
    d._install(table)
    rows = []
    for name in models:
        ph = measure(d, name, args.streams, args.ticks, frames, ch)
        rows.append({"model": name, "streams": args.streams, "us_per_tick": {k: round(v, 1) for k, v in ph.items()},
                     "total_us_per_tick": round(sum(ph.values()), 1)})
        print(f"{name:>8}: " + "  ".join(f"{k} {v:.0f}" for k, v in ph.items()) + f"  total {sum(ph.values()):.0f} us/tick",
              file=sys.stderr, flush=True)
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump({"command": "python bench/daemon_phases.py " + " ".join(argv or sys.argv[1:]), "rows": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
