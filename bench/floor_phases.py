"""Wall microseconds of each phase of a cold 64-stream pass-through tick, in process (issue 19, floor-7).

The real Daemon object (no sockets: its sends collected as bench/daemon_hotpath.py does), fed the
bundles bench/echo_vs_daemon.py's load generator sends (CMU 35_08, left arm missing, an observed
mask with every element), ``--gap-ms`` apart (8: a live tick's cold caches).  Each tick is split
into: ``handle`` (unpack + decode + dispatch of the bundle: Dispatch._take_bytes), ``serve``
(Tick._serve: the array tick, fill maps), ``pack`` (the replies message, as Outbox.flush packs
it).  Median over the ticks, per frame.  ``--sockets``: instead, the whole ``Daemon.turn`` with
its real ROUTER (a DEALER in the same process sends each bundle and reads its replies), wall and
thread CPU.  ``--root`` trees alternate, a round each.

    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python bench/floor_phases.py --root new=. \\
        --root main=/tmp/floor7-main --rounds 4 --ticks 300 --gap-ms 8
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

CHILD = r'''
import json, sys, time
import msgpack
import numpy as np
from daemon import config, wire
from daemon.models import load_all
from daemon.server import Daemon
from mocap.datasets import load_trial
TEST, TRAIN0, MISSING = "35_08", "35_01", ("lhumerus", "lradius", "lwrist", "lhand")
ticks, gap = int(sys.argv[1]), float(sys.argv[2]) / 1000.0
test = load_trial(TEST)
channels = list(load_trial(TRAIN0).channels)
frames = test.frames[:, test.index(channels)].astype(np.float32)
obs = ~np.array([c.split(".")[0] in MISSING for c in channels])
observed = np.broadcast_to(obs, frames.shape)
given = np.where(observed, frames, np.nan).astype(np.float32)  # (what clients/loadgen.py sends)
ab = [given[k].tobytes() for k in range(len(frames))]
mb = [observed[k].astype(np.uint8).tobytes() for k in range(len(frames))]
cfg = config.from_dict({"daemon": {"default_model": "floor", "budget_ms": 1000.0, "max_streams": 4096,
                                   "log_level": "error"},
                        "models": {"floor": {"builtin": "passthrough", "channels": channels}},
                        "zmq": {"router": "tcp://127.0.0.1:*"}})
d = Daemon(cfg)
table, errors = load_all(cfg)
assert not errors
d._install(table)
held = []
d._send = lambda o, m, publish=False: held.append(wire.to_map(m)) if len(o) == 3 else None
d._send_fills = lambda o, maps: held.extend(maps)
pack = msgpack.Packer(use_bin_type=True).pack
ids = [f"p{i}" for i in range(64)]
for sid in ids:
    d._handle(wire.encode(wire.Hello(sid, channels, "floor")), ("router", [b"x"]), time.perf_counter())
d._serve()
held.clear()
T = len(frames)
def body(k):
    fr = [{"stream": ids[i], "seq": k, "t": 1.7e9 + k / 120, "angles": ab[(i * (T // 64) + k) % T],
           "observed": mb[(i * (T // 64) + k) % T]} for i in range(64)]
    return msgpack.packb({"v": 1, "type": "frames", "frames": fr}, use_bin_type=True)
bodies = [body(k) for k in range(ticks + 30)]
origin = ("router", [b"x"], "bundle")
ph = {"handle": [], "serve": [], "pack": [], "tick": []}
pc = time.perf_counter
if sys.argv[3] == "sockets":  # the whole turn with its real sockets: receive, serve, pack, send
    import zmq
    d2 = Daemon(cfg)
    d2.start()
    peer = zmq.Context.instance().socket(zmq.DEALER)
    peer.connect(d2.endpoints()["router"])
    for sid in ids:
        peer.send(wire.encode(wire.Hello(sid, channels, "floor")))
    acks = 0
    while acks < 64:
        ready, arrived = d2._wait()
        d2.turn(d2.clock(), ready, arrived=arrived)
        while peer.poll(0):
            peer.recv()
            acks += 1
    ph = {"turn": [], "turn_cpu": []}
    for k, b in enumerate(bodies):
        peer.send(b)
        ready = d2.net.poll(5000)
        t0, c0 = pc(), time.thread_time()
        d2.turn(d2.clock(), ready)
        t1, c1 = pc(), time.thread_time()
        got = msgpack.unpackb(peer.recv())["replies"]
        assert len(got) == 64 and got[0]["type"] == "fill", got[0]
        if k >= 30:
            ph["turn"].append(t1 - t0)
            ph["turn_cpu"].append(c1 - c0)
        if gap:
            time.sleep(gap)
    print(json.dumps({n: round(float(np.median(v)) * 1e6 / 64, 3) for n, v in ph.items()}))
    sys.exit(0)
for k, b in enumerate(bodies):
    t0 = pc()
    d._take_bytes(b, origin, t0)
    t1 = pc()
    d._serve()
    t2 = pc()
    out = wire.replies_of(held, pack)
    t3 = pc()
    held.clear()
    assert d.metrics.counters.get("frames_out", 0) == 64 * (k + 1), d.metrics.counters
    if k >= 30:
        for n, v in (("handle", t1 - t0), ("serve", t2 - t1), ("pack", t3 - t2), ("tick", t3 - t0)):
            ph[n].append(v)
    if gap:
        time.sleep(gap)
print(json.dumps({n: round(float(np.median(v)) * 1e6 / 64, 3) for n, v in ph.items()}))
'''


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--root", action="append", default=[], metavar="NAME=DIR")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--ticks", type=int, default=300)
    ap.add_argument("--gap-ms", type=float, default=8.0)
    ap.add_argument("--sockets", action="store_true",
                    help="time Daemon.turn with its real sockets instead (a DEALER in process sends each bundle)")
    ap.add_argument("--json", dest="json_out", default=None)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))   # (here, not at the top: a child runs in another tree and imports nothing of this one's)
    from bench.echo_vs_daemon import rotated, tree_env, tree_roots

    roots = tree_roots(args.root)
    names = list(roots)
    rows = []
    for rnd in range(args.rounds):
        for name in rotated(names, rnd):
            env = tree_env(roots[name])
            r = subprocess.run([sys.executable, "-c", CHILD, str(args.ticks), str(args.gap_ms),
                                "sockets" if args.sockets else "phases"], env=env,
                               cwd=roots[name], capture_output=True, text=True, check=False)
            if r.returncode:
                raise RuntimeError(r.stderr[-3000:])
            row = {"round": rnd, "root": name, "loadavg": os.getloadavg()[0],
                   **json.loads(r.stdout.strip().splitlines()[-1])}
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    if args.json_out:
        Path(args.json_out).write_text(json.dumps({"command": " ".join(sys.argv), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
