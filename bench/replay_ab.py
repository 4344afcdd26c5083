"""A daemon behind on single frames, A/B between checkouts: CPU per frame, and the answers.

Each turn reads K single frames of each of 64 streams at once (a daemon that fell behind: a
starved process, a stall), through the public ``Daemon.turn`` of the pass-through filler: the
newest frame of each stream is served, the K - 1 before it are set aside as superseded and
answered ``conflated`` after the fills (daemon/dispatch.py, daemon/aside.py).  Reported: process
CPU microseconds per frame read (each answer encoded to bytes as the transport would), median
of the repeats, and the Python and C calls per frame of one such turn (a count, free of the
machine's load), each tree in its own process (``PYTHONPATH`` = the tree), the trees alternating.

It also plays one fixed mixed burst sequence (interleaved streams, duplicates, late frames,
malformed ones: infinity, a wrong width, not msgpack) in each tree and prints a sha256 of every
answer in the order handed to the transport (drops and errors as their bytes; fills as stream,
seq and values, their ``proc_us`` being a time): equal digests mean equal answers.

    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python bench/replay_ab.py --trees /tmp/integ-replay . --repeats 5
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

CHILD = r'''
import hashlib, json, sys, time
import numpy as np
from daemon import config, wire
from daemon.loop import Daemon
from daemon.models import load_all

K, TURNS, N, C = int(sys.argv[1]), int(sys.argv[2]), 64, 62


class Clock:
    t = 1000.0
    def __call__(self):
        return self.t


def daemon(clock):
    cfg = config.from_dict({"daemon": {"budget_ms": 1000.0, "max_streams": 1000, "log_level": "error", "overdue": "serve"},
                            "models": {"pt": {"builtin": "passthrough"}}, "zmq": {"router": "tcp://127.0.0.1:*"}})
    d = Daemon(cfg, clock=clock)
    table, errors = load_all(cfg)
    assert not errors
    d._install(table)
    return d


def peer(i):
    return ("router", [f"peer-{i}".encode()])


rng = np.random.default_rng(0)
rows = rng.normal(size=(64, C)).astype(np.float32)
rows[:, ::7] = np.nan
clock = Clock()
d = daemon(clock)
out = []
d._send = lambda o, m, publish=False: out.append(wire.encode(m))
for i in range(N):
    d._batch([(wire.encode(wire.Hello(f"s{i}", [f"ch{c}" for c in range(C)])), peer(i), clock())])
seq = 0
def turn_items():
    global seq
    items = []
    for k in range(K):
        seq += 1
        for i in range(N):
            items.append((wire.encode(wire.Frame(f"s{i}", seq, seq / 120, rows[(seq + i) % 64])), peer(i), clock()))
    return items
msgs = [turn_items() for _ in range(20 + TURNS)]
for items in msgs[:20]:
    clock.t += K / 120
    d.turn(clock(), items=items)
    out.clear()
aside = 0
c0 = time.process_time()
for items in msgs[20:]:
    clock.t += K / 120
    aside += d.turn(clock(), items=items)
    out.clear()
cpu = time.process_time() - c0
# Python and C calls of one more such turn, per frame (a count: no timing noise)
ncalls = {"call": 0, "c_call": 0}
def prof(frame, event, arg):
    if event in ncalls:
        ncalls[event] += 1
extra = turn_items()
clock.t += K / 120
sys.setprofile(prof)
d.turn(clock(), items=extra)
sys.setprofile(None)
out.clear()

# the mixed burst sequence, on a fresh daemon: its answers' digest
clock2 = Clock()
d2 = daemon(clock2)
h = hashlib.sha256()
def keep(o, m, publish=False):
    if isinstance(m, wire.FillMsg):
        h.update(repr((o, m.stream, m.seq, m.status, m.angles.tobytes(), m.filled.tobytes(), m.gap)).encode())
    else:
        h.update(repr(o).encode() + wire.encode(m))
d2._send = keep
for i in range(4):
    d2._batch([(wire.encode(wire.Hello(f"s{i}", [f"ch{c}" for c in range(C)])), peer(i), clock2())])
r2 = np.random.default_rng(1)
seqs = [0] * 4
answers_aside = 0
for t in range(30):
    clock2.t += 1 / 120
    items = []
    for _ in range(int(r2.integers(3, 30))):
        i = int(r2.integers(0, 4))
        seqs[i] += int(r2.choice([1, 1, 1, 2, 0, -1]))
        v = rows[int(r2.integers(0, 64))].copy()
        x = r2.random()
        if x < 0.05:
            data = b"\x93not a map"
        elif x < 0.1:
            data = wire.encode(wire.Frame(f"s{i}", max(seqs[i], 0), 0.0, v[:-1]))
        elif x < 0.15:
            v[1] = np.inf
            data = wire.encode(wire.Frame(f"s{i}", max(seqs[i], 0), 0.0, v))
        else:
            data = wire.encode(wire.Frame(f"s{i}", max(seqs[i], 0), 0.0, v))
        items.append((data, peer(i), clock2()))
    answers_aside += d2.turn(clock2(), items=items)
print(json.dumps({"cpu_us_per_frame": 1e6 * cpu / (TURNS * K * N), "set_aside": aside, "frames": TURNS * K * N,
                  "py_calls_per_frame": ncalls["call"] / (K * N), "c_calls_per_frame": ncalls["c_call"] / (K * N),
                  "digest": h.hexdigest(), "digest_set_aside": answers_aside}))
'''


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trees", nargs="+", required=True, help="checkouts, before first")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--behind", type=int, default=8, metavar="K", help="frames of each stream read in each turn")
    ap.add_argument("--turns", type=int, default=60)
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args(argv)
    trees = [Path(t).resolve() for t in args.trees]
    runs: dict[str, list[dict]] = {str(t): [] for t in trees}
    for r in range(args.repeats):
        for t in trees[r % len(trees):] + trees[:r % len(trees)]:  # each tree first in turn
            env = dict(os.environ, PYTHONPATH=str(t), OPENBLAS_NUM_THREADS="1")
            l0 = os.getloadavg()[0]
            p = subprocess.run(["nice", "-n", "5", sys.executable, "-c", CHILD, str(args.behind), str(args.turns)],
                               cwd=t, env=env, capture_output=True, text=True, check=True)
            got = json.loads(p.stdout.strip().splitlines()[-1])
            got["load"] = [l0, os.getloadavg()[0]]
            runs[str(t)].append(got)
            print(f"repeat {r + 1} {t.name}: {json.dumps(got)}", file=sys.stderr, flush=True)
    med = {t: sorted(x["cpu_us_per_frame"] for x in v)[len(v) // 2] for t, v in runs.items()}
    a, b = (str(t) for t in trees[:2]) if len(trees) > 1 else (str(trees[0]),) * 2
    print(f"CPU us per frame, {args.behind} frames of each of 64 streams a turn, median of {args.repeats}: "
          + ", ".join(f"{Path(t).name} {m:.2f}" for t, m in med.items()) + f"; ratio {med[b] / med[a]:.2f}")
    calls = {Path(t).name: (v[0]["py_calls_per_frame"], v[0]["c_calls_per_frame"]) for t, v in runs.items()}
    print(f"calls per frame (Python, C), one turn: {calls}")
    digests = {Path(t).name: {x["digest"] for x in v} for t, v in runs.items()}
    print(f"answer digests: {digests}; {'equal' if len({d for s in digests.values() for d in s}) == 1 else 'DIFFERENT'}")
    if args.json_out:
        Path(args.json_out).write_text(json.dumps({"trees": [str(t) for t in trees], "args": vars(args),
                                                   "median": med, "runs": runs}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
