"""While serving, no full (gen-2) cyclic GC collection runs inside a turn: performers joining
mid-session (their hellos allocate in the turn that also serves the others' frames) cannot set
one off there; housekeeping runs it instead, after the turn's answers, and cyclic garbage is
still reclaimed (daemon/loop.py ``settle``, ``collect_old``; bench/notebook/gc-10.md).

A real daemon with its sockets in a fresh interpreter, started and settled as ``lacuna serve``
does; every collection recorded with ``gc.callbacks``.  The process is first brought to where a
long session gets by itself (many objects survived into the oldest generation, GEN2_EVERY gen-1
collections since the last full one), so the next automatic collection would be a full one."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

SCRIPT = r'''
import gc, json, sys, weakref
import msgpack
import numpy as np
import zmq
from daemon import config, loop, wire

cfg = config.from_dict({"daemon": {"max_streams": 256, "log_level": "error", "budget_ms": 1000.0},
                        "models": {"pt": {"builtin": "passthrough"}}, "zmq": {"router": "tcp://127.0.0.1:*"}})
d = loop.Daemon(cfg)
d.start()
loop.settle()
runs = []
where = {"turn": False, "house": False}
gc.callbacks.append(lambda phase, info: runs.append((info["generation"], where["turn"] and not where["house"]))
                    if phase == "stop" else None)
_turn, _house = loop.Daemon.turn, loop.Daemon._housekeeping
def turn(self, *a, **k):
    where["turn"] = True
    try:
        return _turn(self, *a, **k)
    finally:
        where["turn"] = False
def house(self, now):
    where["house"] = True
    try:
        return _house(self, now)
    finally:
        where["house"] = False
loop.Daemon.turn, loop.Daemon._housekeeping = turn, house

ctx = zmq.Context.instance()
running, joining = ctx.socket(zmq.DEALER), ctx.socket(zmq.DEALER)
for s in (running, joining):
    s.connect(d.endpoints()["router"])
names = [f"c{i}" for i in range(8)]
angles = np.zeros(8, np.float32).tobytes()
def bundle(seq):
    frames = [{"stream": f"run{i}", "seq": seq, "t": 1.0 + seq, "angles": angles} for i in range(4)]
    running.send(msgpack.packb({"v": 1, "type": "frames", "frames": frames}, use_bin_type=True))
def serve_until(n_replies, n_acks):
    got = acks = 0
    for _ in range(10000):
        if got >= n_replies and acks >= n_acks:
            return
        ready, arrived = d._wait()
        d.turn(d.clock(), ready, arrived=arrived)
        while running.poll(0):
            got += len(msgpack.unpackb(running.recv())["replies"])
        while joining.poll(0):
            acks += msgpack.unpackb(joining.recv())["type"] == "hello-ack"
    raise AssertionError(f"{got} replies, {acks} acks")
bundle(0)
serve_until(4, 0)

# a long session's state: survivors in the oldest generation, a full collection due
class Node:
    pass
node = Node()
node.me = node  # cyclic garbage once dropped: only the cyclic GC frees it
gone = weakref.ref(node)
del node
gc.disable()
keep = [[i] for i in range(100000)]
gc.enable()
for _ in range(11):  # (more than GEN2_EVERY, CPython's default gen-2 threshold: 10)
    gc.collect(1)

# 160 performers join mid-session, with the running streams' next frames (enough that young collections
# run in those turns with margin: 64 gave one, and none when a turn took fewer of them)
for i in range(160):
    joining.send(wire.encode(wire.Hello(f"join{i}", names, "pt")))
bundle(1)
serve_until(4, 160)
serving = [g for g, mid in runs if mid]
d._housekeeping(d.clock())  # (the loop runs it every HOUSEKEEPING_S)
print(json.dumps({"gen2_serving": serving.count(2), "young_serving": len(serving) - serving.count(2),
                  "gen2": [g for g, _ in runs].count(2), "reclaimed": gone() is None, "kept": len(keep),
                  "frames_out": d.metrics.counters.get("frames_out")}))
running.close(0)
joining.close(0)
d.close()
'''


def _run(root: Path) -> dict[str, object]:
    env = dict(os.environ, PYTHONPATH=str(root), OPENBLAS_NUM_THREADS="1")
    r = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=120, env=env, cwd=root)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


def test_joining_performers_set_off_no_full_collection_in_a_turn_and_garbage_is_reclaimed():
    out = _run(ROOT)
    assert out["frames_out"] == 8
    assert out["young_serving"] > 0  # the hellos' turns did allocate past the threshold: young collections ran
    assert out["gen2_serving"] == 0
    assert out["gen2"] >= 1  # housekeeping's full collection
    assert out["reclaimed"] is True
