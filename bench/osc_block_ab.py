"""OSC bundles through the daemon in process, the array path (daemon/oscblock.py) against the row
path (python-osc element by element), alternating turn by turn (issue 19; bench/notebook/osc-5.md).

Two in-process daemons of this tree, one with ``sessions.block_path`` off, each with its real OSC
socket; 64 performers' frames of CMU 35_08 (left arm missing, 37 frames apart) as one OSC bundle
a turn (python-osc's builder, as a capture tool sends them), handed to ``Daemon.turn`` as if read,
the fills sent for real to a client UDP socket (drained outside the timing).  Process CPU per
frame served, median over turns; per model.  The HLM: bench/echo_vs_daemon.py's cached file.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/osc_block_ab.py [--turns 600] [--models floor,hlm]
"""
from __future__ import annotations

import argparse
import os
import socket
import tempfile
import time

import numpy as np
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message_builder import OscMessageBuilder

from daemon import budget, config, server
from mocap.datasets import load_trial

ARM = ("lhumerus", "lradius", "lwrist", "lhand")


def _msg(addr, args):
    b = OscMessageBuilder(addr)
    for v, t in args:
        b.add_arg(v, t)
    return b.build()


def _daemon(models, arrays):
    cfg = config.from_dict({"daemon": {"budget_ms": 50.0, "max_streams": 256, "log_level": "error", "max_batch": 64},
                            "models": models, "zmq": {"router": "tcp://127.0.0.1:*"}, "osc": {"listen": "127.0.0.1:0"}})
    d = server.Daemon(cfg, server.Log("error"))
    d.start()
    d.budget = budget.Budget(1e9, 1e9)
    d.sessions.block_path = arrays
    return d


def _drain(u):
    n = 0
    try:
        while True:
            u.recv(1 << 16)
            n += 1
    except BlockingIOError:
        return n


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--turns", type=int, default=600)
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--models", default="floor,hlm")
    ap.add_argument("--hlm", default=os.path.join(tempfile.gettempdir(), "lacuna-echo-vs-daemon", "hlm-5b13b52.npz"))
    ap.add_argument("--default", default=os.path.join(tempfile.gettempdir(), "lacuna-default-block", "default-3501-3506.npz"))
    args = ap.parse_args(argv)
    take = load_trial("35_08")
    ch = list(take.channels)
    x = take.frames.astype(np.float32)
    x[:, [c.split(".")[0] in ARM for c in ch]] = np.nan
    specs = {"floor": {"builtin": "passthrough", "channels": ch}, "hlm": {"file": args.hlm}, "default": {"file": args.default}}
    u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    u.bind(("127.0.0.1", 0))
    u.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 23)
    u.setblocking(False)
    origin = ("osc", u.getsockname())
    n = args.n
    for name in args.models.split(","):
        ds = [_daemon({name: specs[name]}, arrays) for arrays in (False, True)]
        for d in ds:
            hellos = [(_msg("/lacuna/hello", [(f"p{i}", "s"), (name, "s")] + [(c, "s") for c in ch]).dgram, origin, d.clock())
                      for i in range(n)]
            d.turn(d.clock(), items=hellos)
        _drain(u)
        times: list[list[float]] = [[], []]
        for k in range(args.turns + 50):
            bb = OscBundleBuilder(IMMEDIATELY)
            for i in range(n):
                bb.add_content(_msg("/lacuna/frame", [(f"p{i}", "s"), (k, "i"), (k / 120, "d")]
                                    + [(float(v), "f") for v in x[(k + 37 * i) % len(x)]]))
            data = bb.build().dgram
            for w in ((0, 1) if k % 2 else (1, 0)):
                d = ds[w]
                out0 = d.metrics.counters.get("frames_out", 0)
                t0 = time.process_time_ns()
                d.turn(d.clock(), items=[(data, origin, d.clock())])
                dt = time.process_time_ns() - t0
                got = d.metrics.counters.get("frames_out", 0) - out0
                if k >= 50 and got:
                    times[w].append(dt / got / 1e3)
                _drain(u)
        rows, arrays = (float(np.median(t)) for t in times)
        served = ds[1].sessions.block_served
        print(f"{name}: {n} streams, {args.turns} turns: row path {rows:.1f} us/frame, array path {arrays:.1f} us/frame, "
              f"array/row {arrays / rows:.3f} (bundles served as arrays: {served}, row daemon {ds[0].sessions.block_served}); "
              f"load {os.getloadavg()[0]:.2f}")
        for d in ds:
            d.close()
    u.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
