"""Daemon round-trip latency over ZeroMQ request/reply on loopback (the `## Daemon` figures).

Starts `lacuna serve` as a child process with three models: the pass-through floor, hold
(hold-last-value) and nn (nearest neighbour, 9478 training frames x 62 channels of the pan2009
training set), plus any model files given with --model NAME=FILE (HLM/CRBM when they exist).
Each scenario drives N streams at R Hz with one DEALER socket per stream
(clients.loadgen.run_load) replaying a real held-out walk with the left arm and the head
missing, and records every frame's round trip.  Repeats give medians of the percentiles.

    .venv/bin/python bench/daemon_latency.py --seconds 10 --repeats 3 --json bench/daemon_latency.json

Progress lines go to stderr; the JSON holds every run.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile

import numpy as np

from clients import loadgen
from clients.control import control
from clients.harness import DaemonProcess
from lacuna.errors import LacunaError
from mocap.baselines import HoldModel, NearestNeighbourModel
from mocap.protocols import get_protocol

MISSING_PREFIXES = ("lclavicle", "lhumerus", "lradius", "lwrist", "lhand", "lfingers", "lthumb", "head", "upperneck")


def rss_kib(pid: int) -> int:
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return -1


def cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as fh:
        f = fh.read().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--rate", type=float, default=120.0)
    ap.add_argument("--streams", default="1,64", help="comma-separated stream counts")
    ap.add_argument("--models", default="floor,hold,nn", help="models to measure (floor = pass-through)")
    ap.add_argument("--model", action="append", default=[], metavar="NAME=FILE", help="extra model file")
    ap.add_argument("--budget-ms", type=float, default=4.0)
    ap.add_argument("--overload", action="store_true", help="also offer 64 streams at 4x the rate with the hold model")
    ap.add_argument("--max-in-flight", type=int, default=4,
                    help="unanswered frames per stream before the generator skips one (a plugin's bound)")
    ap.add_argument("--json", dest="json_out", help="write results here")
    args = ap.parse_args(argv)

    ts = get_protocol("pan2009").training_set()
    case = get_protocol("pan2009").cases()[0]
    truth = np.asarray(case.truth if hasattr(case, "truth") else case.frames, dtype=np.float32)
    channels = list(ts.channels)
    missing = np.array([c.split(".")[0] in MISSING_PREFIXES for c in channels])
    frames = truth.copy()
    frames[:, missing] = np.nan
    tmp = tempfile.mkdtemp(prefix="lacuna-bench-")
    HoldModel.fit(ts.sequences, channels).save(f"{tmp}/hold.npz")
    NearestNeighbourModel.fit(ts.sequences, channels).save(f"{tmp}/nn.npz")
    lines = ["[daemon]", f"budget_ms = {args.budget_ms}", "max_streams = 4096", "log_level = \"warning\"",
             "default_model = \"floor\"", "[models.floor]", "builtin = \"passthrough\"",
             "[models.hold]", f"file = \"{tmp}/hold.npz\"", "[models.nn]", f"file = \"{tmp}/nn.npz\""]
    for spec in args.model:
        name, path = spec.split("=", 1)
        lines += [f"[models.{name}]", f"file = \"{os.path.abspath(path)}\""]
    lines += ["[zmq]", "router = \"tcp://127.0.0.1:*\""]
    with open(f"{tmp}/bench.toml", "w") as fh:
        fh.write("\n".join(lines) + "\n")

    machine = {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(), "python": platform.python_version(),
               "note": "2-core machine shared with other jobs; compare ratios within one run"}
    try:
        with open("/proc/cpuinfo") as fh:
            machine["cpu"] = next(ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    results = []
    models = args.models.split(",") + [s.split("=", 1)[0] for s in args.model]
    with DaemonProcess(f"{tmp}/bench.toml", env={"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}) as d:
        ep = d.endpoints["router"]
        pid = d.proc.pid
        scenarios = [(int(n), args.rate, m) for n in args.streams.split(",") for m in models]
        if args.overload:
            scenarios.append((64, 4 * args.rate, "hold"))
        k = 0
        for n, rate, model in scenarios:
            for rep in range(args.repeats):
                k += 1
                rss0, cpu0 = rss_kib(pid), cpu_s(pid)
                c0 = control(ep, "status", timeout_s=5.0).result["counters"]
                res = loadgen.run_load(ep, channels, frames, n_streams=n, rate=rate, seconds=args.seconds, model=model,
                                       prefix=f"{model}-{n}-{rep}", max_in_flight=args.max_in_flight,
                                       warmup_s=0.5, drain_s=2.0, progress=False)
                row = {"streams": n, "rate_hz": rate, "model": model, "repeat": rep, **res.summary(),
                       "offered_fps": round(res.sent / max(res.seconds, 1e-9), 1),
                       "served_fps": round(res.served / max(res.seconds, 1e-9), 1),
                       "load_average": os.getloadavg()[0],
                       "daemon_cpu_percent": round(100 * (cpu_s(pid) - cpu0) / res.seconds, 1),
                       # CPU the daemon spent per frame it answered (fills and drops, warm-up
                       # included): a cost figure that scheduling noise on a shared machine hardly moves
                       "daemon_cpu_us_per_frame": round(1e6 * (cpu_s(pid) - cpu0) / max(1, res.served + res.dropped + int(
                           0.5 * rate * n)), 1),
                       "daemon_rss_kib_before": rss0, "daemon_rss_kib_after": rss_kib(pid)}
                c1 = control(ep, "status", timeout_s=5.0).result["counters"]
                for key in ("degraded_held", "degraded_iterations", "send_dropped", "dropped_conflated"):
                    row[f"daemon_{key}"] = c1.get(key, 0) - c0.get(key, 0)
                results.append(row)
                print(f"[{k}/{len(scenarios) * args.repeats}] {model:>6} {n:>3} streams @ {rate:g} Hz: "
                      f"p50 {row['p50_ms']:.3f} p99 {row['p99_ms']:.3f} max {row['max_ms']} ms, served {row['served']} "
                      f"degraded {row['degraded']} dropped {row['dropped']} lost {row['lost']} cpu {row['daemon_cpu_percent']}%",
                      file=sys.stderr, flush=True)
                # the streams of this run go idle; a reset keeps the session table small
                for i in range(n):
                    try:
                        control(ep, "reset", f"{model}-{n}-{rep}-{i:03d}", timeout_s=2)
                    except LacunaError:
                        pass
    summary = []
    for n, rate, model in scenarios:
        rows = [r for r in results if (r["streams"], r["rate_hz"], r["model"]) == (n, rate, model)]
        summary.append({"streams": n, "rate_hz": rate, "model": model,
                        **{k: float(np.median([r[k] for r in rows])) for k in ("p50_ms", "p90_ms", "p99_ms", "p999_ms", "max_ms",
                                                                                "daemon_cpu_percent", "daemon_cpu_us_per_frame", "offered_fps", "served_fps",
                                                                                "load_average")},
                        "daemon_proc_p99_ms": float(np.median([r["daemon_proc_p99_ms"] or np.nan for r in rows])),
                        "served": sum(r["served"] for r in rows), "unsent": sum(r["unsent"] for r in rows),
                        **{f"daemon_{k}": sum(r[f"daemon_{k}"] for r in rows)
                           for k in ("degraded_held", "degraded_iterations", "send_dropped", "dropped_conflated")}, "degraded": sum(r["degraded"] for r in rows),
                        "dropped": sum(r["dropped"] for r in rows), "lost": sum(r["lost"] for r in rows),
                        "rss_kib_first": rows[0]["daemon_rss_kib_before"], "rss_kib_last": rows[-1]["daemon_rss_kib_after"]})
    out = {"machine": machine, "seconds": args.seconds, "repeats": args.repeats, "budget_ms": args.budget_ms,
           "command": "python bench/daemon_latency.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "summary": summary, "runs": results}
    print(json.dumps(summary, indent=1))
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump(out, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
