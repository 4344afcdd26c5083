"""A live ``lacuna serve`` pass-through at one stream of 120 Hz, its turns timed part by part (issue 19).

Where a single frame's time goes in the real daemon process with real sockets: the daemon runs under a
small wrapper (its ``Daemon.turn``, ``Transports.receive`` (read, decode, hand to the session),
``Tick._serve``, ``Tick._answer`` (encode, queue the reply, accounting), ``Daemon._send_held`` and
``Outbox.flush`` (ZeroMQ send) timed with perf_counter, and each turn's thread CPU), driven by the load
generator of bench/echo_vs_daemon.py (CMU 35_08, the left arm missing).  The wrappers cost a few
microseconds a call.  ``--config KEY=VALUE`` sets a ``[daemon]`` value (JSON), e.g. ``prewarm_ms=0``.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/single_turn.py --seconds 8 [--config prewarm_spin_ms=0] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
START_S = 300  # a first start after an install compiles the kernels (clients/harness.py)

CHILD = r'''
import sys, os, json, atexit, time
sys.path.insert(0, os.environ["PYTHONPATH"])
from daemon import loop, outbox, tick, transport
pc, tt = time.perf_counter, time.thread_time
T, SUB = [], {}
_turn = loop.Daemon.turn
def turn(self, now, ready=None, items=None, arrived=None):
    t, c = pc(), tt()
    r = _turn(self, now, ready, items, arrived)
    T.append((pc() - t, tt() - c, bool(ready)))
    return r
loop.Daemon.turn = turn
def wrap(cls, name):
    f = getattr(cls, name)
    acc = SUB.setdefault(name, [])
    def w(self, *a, **k):
        t = pc(); r = f(self, *a, **k); acc.append(pc() - t); return r
    setattr(cls, name, w)
wrap(transport.Transports, "receive")
wrap(tick.Tick, "_serve")
wrap(tick.Tick, "_answer")
wrap(loop.Daemon, "_send_held")
wrap(outbox.Outbox, "flush")
atexit.register(lambda: json.dump({"turns": T, "sub": SUB}, open(sys.argv[1], "w")))
from daemon.loop import serve
sys.exit(serve(sys.argv[2]))
'''


def pct(a: list[float]) -> dict[str, float]:
    x = np.asarray(a) * 1e6
    return {f"p{q}": round(float(np.percentile(x, q)), 1) for q in (10, 50, 90, 99)} if x.size else {}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--config", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--json", dest="json_out")
    a = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    from bench.echo_vs_daemon import MISSING, TEST, TRAIN, tree_env
    from clients import loadgen
    from clients.client import control
    from clients.harness import DaemonProcess
    from mocap.datasets import load_trial

    test = load_trial(TEST)
    channels = list(load_trial(TRAIN[0]).channels)
    frames = test.frames[:, test.index(channels)].astype(np.float32)
    observed = np.broadcast_to(~np.array([c.split(".")[0] in MISSING for c in channels]), frames.shape).copy()
    work = Path(tempfile.mkdtemp(prefix="single-turn-"))
    extra = {k: json.loads(v) for k, v in (x.split("=", 1) for x in a.config)}
    child, trace = work / "child.py", work / "trace.json"
    child.write_text(CHILD)
    d = DaemonProcess({"floor": {"builtin": "passthrough", "channels": channels}}, workdir=str(work),
                      daemon={"budget_ms": 4.0, "log_level": "warning", **extra}, env=tree_env(ROOT),
                      argv=[sys.executable, str(child), str(trace)])
    with d.start(START_S):
        load0 = os.getloadavg()[0]
        res = loadgen.run_load(d.endpoint, channels, frames, observed, n_streams=1, rate=120.0, seconds=a.seconds,
                               model="floor", prefix="st", progress=False)
        st = control(d.endpoint, "status", timeout_s=5.0).result
    tr = json.loads(trace.read_text())
    read = [t for t in tr["turns"] if t[2]]
    out = {"command": " ".join(sys.argv), "at": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "load": [load0, os.getloadavg()[0]], "config": extra, "rtt_ms": loadgen.percentiles(res.rtt_ms),
           "sent": res.sent, "served": res.served, "prewarm": st.get("prewarm"),
           "turns_with_a_frame": len(read), "turn_wall_us": pct([t[0] for t in read]), "turn_cpu_us": pct([t[1] for t in read]),
           "empty_turn_wall_us": pct([t[0] for t in tr["turns"] if not t[2]]),
           "parts_us": {k: pct(v) for k, v in tr["sub"].items()}}
    print(json.dumps(out, indent=1))
    if a.json_out:
        Path(a.json_out).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
