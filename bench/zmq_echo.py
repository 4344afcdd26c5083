"""What any Python ROUTER server can do on this machine: the load generator against a bare echo.

The echo server is a separate process with one ROUTER socket: it reads every waiting request,
answers each with a reply shaped like the daemon's fill (msgpack map, same byte fields; a
``frames`` bundle with one ``replies`` message, as the daemon does), and
sends the answers back to back.  No numpy, no sessions, no scheduler: it is the floor under
the daemon's own pass-through floor (``lacuna bench --floor``), measured with the same load
generator (``clients.loadgen``), the same take and the same streams x rate.

    .venv/bin/python bench/zmq_echo.py [--streams 64] [--rate 120] [--seconds 10] [--repeats 3] [--json OUT]

For each repeat it runs the load once with one DEALER per stream and once with every stream
down one DEALER (``--connections 1``), and reports p50/p90/p99 of the round trip and the echo
server's CPU per frame.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

ECHO = r'''
import sys, time, msgpack, zmq
ctx = zmq.Context()
r = ctx.socket(zmq.ROUTER)
r.setsockopt(zmq.ROUTER_MANDATORY, 1)
r.setsockopt(zmq.SNDHWM, 10000)
r.setsockopt(zmq.RCVHWM, 10000)
r.bind(sys.argv[1])
print("ready", flush=True)
pack = msgpack.Packer(use_bin_type=True).pack
n = 0


def fill(m):
    return {"v": 1, "type": "fill", "stream": m["stream"], "seq": m["seq"], "t": m["t"], "angles": m["angles"],
            "filled": m["observed"], "std": m["angles"], "status": "passthrough", "model": "echo", "proc_us": 0}


while True:
    if not r.poll(5000):
        break
    got = []
    while True:
        try:
            got.append(r.recv_multipart(zmq.NOBLOCK))
        except zmq.Again:
            break
    out = []
    for parts in got:
        m = msgpack.unpackb(parts[-1])
        if m["type"] == "hello":
            body = pack({"v": 1, "type": "hello-ack", "stream": m["stream"], "model": "echo",
                         "channels": m["channels"], "passthrough": [], "missing": []})
        elif m["type"] == "frames":  # a bundle: one replies message, each answer a complete fill
            body = pack({"v": 1, "type": "replies", "replies": [fill(f) for f in m["frames"]]})
            n += len(m["frames"])
        else:
            body = pack(fill(m))
            n += 1
        out.append([parts[0], body])
    for o in out:
        r.send_multipart(o, zmq.NOBLOCK)
print(f"frames {n} cpu {time.process_time()}", flush=True)
'''


def one(streams: int, rate: float, seconds: float, connections: int | None, channels: list[str],
        frames: np.ndarray, observed: np.ndarray) -> dict:
    from clients import loadgen
    from clients.configfile import free_port

    ep = f"tcp://127.0.0.1:{free_port()}"
    srv = subprocess.Popen([sys.executable, "-c", ECHO, ep], stdout=subprocess.PIPE, text=True)
    try:
        assert srv.stdout is not None and srv.stdout.readline().strip() == "ready"
        res = loadgen.run_load(ep, channels, frames, observed, n_streams=streams, rate=rate, seconds=seconds,
                               progress=False, connections=connections)
        srv.wait(30)
        tail = srv.stdout.read().split()
        cpu_s = float(tail[tail.index("cpu") + 1])
    finally:
        if srv.poll() is None:
            srv.kill()
    return {"connections": connections or streams, **loadgen.percentiles(res.rtt_ms), "served": res.served,
            "sent": res.sent, "echo_cpu_us_per_frame": 1e6 * cpu_s / max(1, res.served)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--streams", type=int, default=64)
    ap.add_argument("--rate", type=float, default=120.0)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args(argv)
    from clients.bench import bench_take
    from clients.synth import CMU_CHANNELS

    channels = list(CMU_CHANNELS)
    frames, observed, src = bench_take(channels, 0)
    rows = []
    for r in range(args.repeats):
        for conns in (None, 1):
            row = one(args.streams, args.rate, args.seconds, conns, channels, frames, observed)
            rows.append(row)
            print(f"repeat {r}: {args.streams} streams x {args.rate:g} Hz, {row['connections']} connection(s): "
                  f"p50 {row['p50_ms']:.3f} p90 {row['p90_ms']:.3f} p99 {row['p99_ms']:.3f} ms, "
                  f"echo CPU {row['echo_cpu_us_per_frame']:.1f} us/frame, served {row['served']}/{row['sent']}",
                  file=sys.stderr, flush=True)
    summary = {}
    for conns in sorted({r["connections"] for r in rows}):
        rs = [r for r in rows if r["connections"] == conns]
        summary[str(conns)] = {k: float(np.median([r[k] for r in rs]))
                               for k in ("p50_ms", "p90_ms", "p99_ms", "echo_cpu_us_per_frame")}
        summary[str(conns)]["p99_range"] = [min(r["p99_ms"] for r in rs), max(r["p99_ms"] for r in rs)]
    out = {"command": "python bench/zmq_echo.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "take": src, "streams": args.streams, "rate": args.rate, "seconds": args.seconds,
           "repeats": args.repeats, "at": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "loadavg": Path("/proc/loadavg").read_text().split()[:3] if os.path.exists("/proc/loadavg") else None,
           "summary": summary, "runs": rows}
    print(json.dumps(summary, indent=1))
    if args.json_out:
        Path(args.json_out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
