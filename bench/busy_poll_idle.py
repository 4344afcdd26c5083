"""What busy_poll_ms costs: the daemon's CPU while frames flow and once they stop.

tests/test_daemon_e2e.py checks the behaviour (busy-polling answers as without it, and the
serving thread goes back to sleeping in poll once the traffic pauses); this measures the CPU
that figure used to assert (under 0.3 s of CPU in 1 s idle).  For each setting of
``--busy-poll`` (ms; 0 = off), alternating setting by setting ``--repeats`` times: a daemon
process with a hold model, ``--frames`` lock-step round trips on one DEALER, then ``--idle``
seconds without traffic.  Reports per setting the median over repeats of the daemon's CPU
seconds per second of wall time while frames flowed and while idle, and the round trip p50.

    .venv/bin/python bench/busy_poll_idle.py --repeats 3 --busy-poll 0 50 --json bench/results/busy_poll_idle.json

CPU comes from /proc/<pid>/stat (Linux).  On a shared machine the idle figure is the cleaner
one (a spinning daemon takes whatever core it gets: near 1.0); the busy one depends on load.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import zmq

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from clients.daemon_proc import cpu_seconds
from daemon import loadgen, wire
from mocap.baselines import HoldModel

CH = [f"c{i}.rx" for i in range(8)]


def one_run(busy_ms: float, frames: int, idle_s: float) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        HoldModel(CH, np.zeros(len(CH)), np.ones(len(CH))).save(f"{tmp}/h.npz")
        cfg = Path(tmp) / "lacuna.toml"
        cfg.write_text(f"[daemon]\nbudget_ms = 250.0\nbusy_poll_ms = {busy_ms:g}\nlog_level = \"warning\"\n"
                       f"[models.h]\nfile = \"{tmp}/h.npz\"\n[zmq]\nrouter = \"tcp://127.0.0.1:*\"\n")
        d = loadgen.DaemonProcess(str(cfg)).start()
        ctx = zmq.Context()
        s = ctx.socket(zmq.DEALER)
        s.setsockopt(zmq.LINGER, 0)
        try:
            s.connect(d.endpoints["router"])
            row = np.arange(len(CH), dtype=np.float32)
            row[0] = np.nan
            rtt = []
            c0, w0 = cpu_seconds(d.proc.pid), time.perf_counter()
            for seq in range(frames):
                t = time.perf_counter()
                s.send(wire.encode(wire.Frame("b", seq, seq / 120.0, row)))
                if not s.poll(10_000):
                    raise TimeoutError(f"frame {seq} not answered")
                s.recv()
                rtt.append(time.perf_counter() - t)
            c1, w1 = cpu_seconds(d.proc.pid), time.perf_counter()
            time.sleep(idle_s)  # the measurement: idle wall time
            c2, w2 = cpu_seconds(d.proc.pid), time.perf_counter()
        finally:
            s.close(0)
            ctx.term()
            d.stop()
    assert None not in (c0, c1, c2), "no /proc/<pid>/stat"
    return {"busy_cpu_per_s": (c1 - c0) / (w1 - w0), "idle_cpu_per_s": (c2 - c1) / (w2 - w1),
            "rtt_p50_ms": 1000 * float(np.median(rtt)), "load_avg_1min": os.getloadavg()[0]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--busy-poll", type=float, nargs="+", default=[0.0, 50.0], metavar="MS")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--idle", type=float, default=2.0, metavar="S")
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args(argv)
    runs: dict[str, list[dict[str, float]]] = {f"{b:g}": [] for b in args.busy_poll}
    for r in range(args.repeats):
        for b in args.busy_poll:  # alternating: a busy spell of the machine falls on every setting
            x = one_run(b, args.frames, args.idle)
            runs[f"{b:g}"].append(x)
            print(f"repeat {r + 1}/{args.repeats} busy_poll_ms {b:g}: " + ", ".join(f"{k} {v:.3f}" for k, v in x.items()),
                  file=sys.stderr, flush=True)
    print("| busy_poll_ms | runs | CPU s/s while frames flow | CPU s/s idle | round trip p50 ms |\n|---|---|---|---|---|")
    med = {}
    for b, xs in runs.items():
        med[b] = {k: float(np.median([x[k] for x in xs])) for k in xs[0]}
        m = med[b]
        print(f"| {b} | {len(xs)} | {m['busy_cpu_per_s']:.2f} | {m['idle_cpu_per_s']:.3f} | {m['rtt_p50_ms']:.3f} |")
    if args.json_out:
        Path(args.json_out).write_text(json.dumps({
            "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "args": vars(args),
            "machine": {"python": platform.python_version(), "cpus": os.cpu_count(), "platform": platform.platform()},
            "median": med, "runs": runs}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
