"""A serving daemon imports nothing: what its turns load on first use is loaded before the first
frame (daemon/loop.py ``settle``), not in the middle of a turn (a first import there took 12-20 ms
live at 64 streams, and the bundles of that turn were dropped: bench/notebook/floor-7.md).

Run in a fresh interpreter (another test may have imported the modules already): a real daemon
with its sockets, started and settled as ``lacuna serve`` does, real frames through its real
turns, then its housekeeping with those frames' latencies in the tables."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

SCRIPT = r'''
import json, sys, time
import msgpack
import numpy as np
import zmq
from daemon import config, loop

cfg = config.from_dict({"daemon": {"max_streams": 8, "log_level": "error", "budget_ms": 1000.0},
                        "models": {"pt": {"builtin": "passthrough"}}, "zmq": {"router": "tcp://127.0.0.1:*"}})
d = loop.Daemon(cfg)
d.start()
if sys.argv[1] == "settle":
    loop.settle()
else:  # (numba, imported at start for the compiled wire path, loads numpy.ma itself: forget it, so that
    # the first percentile loads it again as it did before: what settle is there to do before any frame)
    for name in [m for m in sys.modules if m == "numpy.ma" or m.startswith("numpy.ma.")]:
        del sys.modules[name]
    if "ma" in vars(np):
        delattr(np, "ma")
ctx = zmq.Context.instance()
peer = ctx.socket(zmq.DEALER)
peer.connect(d.endpoints()["router"])
before = set(sys.modules)
angles = np.zeros(4, np.float32).tobytes()
for seq in range(3):
    frames = [{"stream": f"s{i}", "seq": seq, "t": 1.0 + seq, "angles": angles} for i in range(4)]
    peer.send(msgpack.packb({"v": 1, "type": "frames", "frames": frames}, use_bin_type=True))
    got = 0
    while got < 4:
        ready, arrived = d._wait()
        d.turn(d.clock(), ready, arrived=arrived)
        if peer.poll(0):
            got += len(msgpack.unpackb(peer.recv())["replies"])
assert d.metrics.counters.get("frames_out") == 12, d.metrics.counters
d._housekeeping(d.clock())
print(json.dumps(sorted(set(sys.modules) - before)))
peer.close(0)
d.close()
'''


def _imported(mode: str) -> list[str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1")
    r = subprocess.run([sys.executable, "-c", SCRIPT, mode], capture_output=True, text=True, timeout=120, env=env,
                       cwd=ROOT)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_serving_and_housekeeping_import_nothing_after_settle():
    assert _imported("settle") == []


def test_without_settle_the_first_housekeeping_imports():
    # (the check above can fail: without settle, the first percentile imports in the turn)
    assert any(m.startswith("numpy.ma") for m in _imported("none"))
