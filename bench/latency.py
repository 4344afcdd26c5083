"""Fill bench/NOTEBOOK.md `## Daemon latency (lacuna bench)` with `lacuna bench` measurements.

    .venv/bin/python bench/latency.py [--repeats 3] [--seconds 10] [--waits sleep,busy] [--out bench/out] [--no-write]

For each model (hold, nn, and HLM / CRBM when this build registers them; all trained on the
same handful of real CMU walks), each load (1 stream at 120 Hz; 64 streams at 120 Hz, one DEALER
per stream; 64 streams at 120 Hz down one DEALER, ``64x120/1``) and each
way of waiting (``sleep``: both sides sleep in poll, the default; ``busy``: ``--busy-poll 50``,
daemon and client spin on their sockets) it runs
``lacuna bench --model FILE --floor`` ``--repeats`` times (a fresh daemon each time) and records
the median over repeats of every percentile, the spread of p99, the counts and the daemon's
CPU, beside the pass-through floor measured in the same run.  Per-run JSON and histogram PNGs
go to ``--out``; the table replaces the section in bench/NOTEBOOK.md.
"""
from __future__ import annotations

import argparse
import json
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from lacuna import registry  # noqa: E402
from lacuna.cli import main as lacuna  # noqa: E402
from mocap.protocols import TrainingSet  # noqa: E402

SECTION = "## Daemon latency (lacuna bench)"
TRAIN = ["35_01", "35_06", "35_07", "35_08", "35_09", "35_10", "35_11", "35_12"]
LOADS = [(1, 120.0, None, False), (64, 120.0, None, False), (64, 120.0, 1, False)]  # (streams, Hz, connections
# (None = one each), bundled)
OPTIONS = {"fps": 120.0, "cycle_frames": 140}
SMALL = {"hlm": {"n_iter": 10, "styles": 2, "restarts": 1, "progress": False},
         "crbm": {"hidden": 100, "epochs": 40, "order": 3, "progress": False}}


def train_models(out: Path, names: list[str]) -> dict[str, Path]:
    from mocap.datasets import load_trial

    ms = [load_trial(t) for t in TRAIN]
    ts = TrainingSet([m.frames for m in ms], ms[0].channels, 120.0, TRAIN, ["walk"] * len(ms))
    files = {}
    for name in names:
        if name not in registry.methods():
            print(f"{name}: not registered in this build, skipped", file=sys.stderr)
            continue
        f = out / f"{name}.npz"
        if not f.exists():
            t0 = time.perf_counter()
            spec = registry.get_method(name)
            spec.train(ts, **{**OPTIONS, **spec.defaults, **SMALL.get(name, {})}).save(str(f))
            print(f"trained {name} in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        files[name] = f
    return files


BUSY_POLL_MS = 50.0


def run(files: dict[str, Path], out: Path, repeats: int, seconds: float, waits: list[str],
        cpu_latency: int | None = None, realtime: int | None = None) -> list[dict]:
    rows = []
    for name, f in files.items():
        for streams, rate, conns, bundle in LOADS:
            for wait in waits:
                reps = []
                for r in range(repeats):
                    tag = f"{streams}x{rate:g}" + (f"c{conns}" if conns else "") + ("b" if bundle else "") + \
                        (f"-q{cpu_latency}" if cpu_latency is not None else "") + (f"-rt{realtime}" if realtime else "")
                    j = out / f"{name}-{tag}-{wait}-r{r}.json"
                    cmd = ["bench", "--streams", str(streams), "--rate", str(rate), "--seconds", str(seconds),
                           "--model", str(f), "--floor", "--json", str(j), "--plot", str(j.with_suffix(".png")), "-q"]
                    if conns:
                        cmd += ["--connections", str(conns)]
                    if bundle:
                        cmd += ["--bundle"]
                    if cpu_latency is not None:
                        cmd += ["--cpu-latency", str(cpu_latency)]
                    if realtime:
                        cmd += ["--realtime", str(realtime)]
                    if wait == "busy":
                        cmd += ["--busy-poll", f"{BUSY_POLL_MS:g}"]
                    print(f"lacuna {' '.join(cmd)}", file=sys.stderr, flush=True)
                    if lacuna(cmd) != 0:
                        raise SystemExit(f"bench run failed: {cmd}")
                    reps.append(json.loads(j.read_text()))
                rows.append({**summarise(name, streams, rate, seconds, reps), "wait": wait,
                             "connections": conns or streams, "bundle": bundle, "cpu_latency_us": cpu_latency,
                             "cpu_latency_held": all((r.get("cpu_latency") or {}).get("held") for r in reps),
                             "realtime": realtime, "realtime_held": all((r.get("realtime") or {}).get("held") for r in reps)})
    return rows


def summarise(name: str, streams: int, rate: float, seconds: float, reps: list[dict]) -> dict:
    def med(run: str, key: str) -> float | None:
        v = [r["runs"][run][key] for r in reps if r["runs"][run][key] is not None]
        return float(np.median(v)) if v else None

    def spread(run: str, key: str) -> tuple[float, float]:
        v = [r["runs"][run][key] for r in reps]
        return float(min(v)), float(max(v))

    out = {"name": name, "streams": streams, "rate": rate, "seconds": seconds, "repeats": len(reps)}
    for run in ("model", "floor"):
        out[run] = {k: med(run, k) for k in ("p50_ms", "p90_ms", "p99_ms", "p999_ms", "max_ms", "cpu_percent",
                                             "daemon_proc_ms_p50", "daemon_rss_growth_mb")}
        out[run]["p99_range"] = spread(run, "p99_ms")
        out[run]["served"] = sum(r["runs"][run]["served"] for r in reps)
        out[run]["offered"] = sum(r["runs"][run]["offered"] for r in reps)
        out[run]["degraded"] = sum(r["runs"][run]["degraded"] for r in reps)
        out[run]["dropped"] = sum(r["runs"][run]["dropped"] for r in reps)
        out[run]["counts_agree"] = all(r["runs"][run]["counts_agree"] for r in reps)
    return out


def table(rows: list[dict], repeats: int, seconds: float) -> str:
    head = ("| model | load | wait | p50 | p90 | p99 (range) | p99.9 | max | served / offered | degraded | dropped | daemon CPU |"
            "\n|---|---|---|---|---|---|---|---|---|---|---|---|")
    L = [head]
    for r in rows:
        for run in ("model", "floor"):
            m = r[run]
            label = r["name"] if run == "model" else "pass-through floor"
            f = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
            cpu = "-" if m["cpu_percent"] is None else f"{m['cpu_percent']:.0f}%"
            conns = r.get("connections", r["streams"])
            load = f"{r['streams']} x {r['rate']:g} Hz" + (f", {conns} conn." if conns != r["streams"] else "") + \
                (", bundled" if r.get("bundle") else "")
            if r.get("cpu_latency_us") is not None:
                load += f", cpu_latency {r['cpu_latency_us']} µs" + ("" if r.get("cpu_latency_held") else " (REFUSED)")
            if r.get("realtime"):
                load += f", SCHED_RR {r['realtime']}" + ("" if r.get("realtime_held") else " (REFUSED)")
            L.append(f"| {label} | {load} | {r.get('wait', 'sleep')} | {f(m['p50_ms'])} | {f(m['p90_ms'])} | "
                     f"{f(m['p99_ms'])} ({m['p99_range'][0]:.2f}-{m['p99_range'][1]:.2f}) | {f(m['p999_ms'])} | "
                     f"{f(m['max_ms'])} | {m['served']} / {m['offered']} | {m['degraded']} | {m['dropped']} | "
                     f"{cpu} |")
    return "\n".join(L)


def write_section(text: str) -> None:
    p = ROOT / "bench" / "NOTEBOOK.md"  # the dated runs (docs/BENCHMARKS.md is the short page for users)
    doc = p.read_text()
    i = doc.index(SECTION)
    m = re.search(r"^## ", doc[i + len(SECTION):], flags=re.M)
    rest = "" if m is None else "\n" + doc[i + len(SECTION) + m.start():]
    p.write_text(doc[:i] + SECTION + "\n\n" + text.strip() + "\n" + rest)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--out", default=str(ROOT / "bench" / "out"))
    ap.add_argument("--note", default="", help="a sentence added under the table (e.g. which branches were measured)")
    ap.add_argument("--models", default="hold,nn,hlm,crbm", help="comma-separated (default hold,nn,hlm,crbm)")
    ap.add_argument("--loads", default="1x120,64x120,64x120/1",
                    help="comma-separated STREAMSxHZ[/CONNECTIONS[b]] (default 1x120,64x120,64x120/1: one DEALER per "
                         "stream, and 64 streams down one connection; a trailing b sends each connection's frames "
                         "of a tick as one bundle, 64x120/1b)")
    ap.add_argument("--cpu-latency", type=int, default=None, metavar="US",
                    help="every daemon holds a PM QoS CPU latency request of US µs (lacuna bench --cpu-latency)")
    ap.add_argument("--realtime", type=int, default=None, metavar="PRIO",
                    help="every daemon's serving threads run SCHED_RR at PRIO (lacuna bench --realtime)")
    ap.add_argument("--waits", default="sleep,busy",
                    help=f"comma-separated: sleep (both sides sleep in poll), busy (--busy-poll {BUSY_POLL_MS:g}: both spin)")
    ap.add_argument("--no-write", action="store_true", help="print the section instead of writing bench/NOTEBOOK.md")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    global LOADS
    LOADS = []
    for x in args.loads.split(","):
        load, _, conns = x.partition("/")
        a, b = load.split("x")
        bundle = conns.endswith("b")
        conns = conns.rstrip("b")
        LOADS.append((int(a), float(b), int(conns) if conns else (int(a) if bundle else None), bundle))
    files = {k: v for k, v in train_models(out, args.models.split(",")).items()}
    t0 = time.time()
    waits = args.waits.split(",")
    if not set(waits) <= {"sleep", "busy"}:
        raise SystemExit(f"--waits takes sleep and/or busy (got {args.waits})")
    rows = run(files, out, args.repeats, args.seconds, waits, args.cpu_latency, args.realtime)
    (out / "latency-summary.json").write_text(json.dumps(rows, indent=2))
    load = subprocess.run(["cat", "/proc/loadavg"], capture_output=True, text=True).stdout.split()[:3]
    text = "\n".join([
        f"Measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime(t0))} with "
        f"`.venv/bin/python bench/latency.py --repeats {args.repeats} --seconds {args.seconds:g} "
        f"--models {args.models} --loads {args.loads} --waits {args.waits}"
        + (f" --cpu-latency {args.cpu_latency}" if args.cpu_latency is not None else "")
        + (f" --realtime {args.realtime}" if args.realtime else "") + "` "
        f"(each row: `lacuna bench --streams N --rate 120 --seconds {args.seconds:g} --model FILE --floor`, "
        f"with `--connections 1` where the load says 1 conn. (every stream down one DEALER, as one capture "
        f"system would send them; otherwise one DEALER per stream), `--bundle` where it says bundled (each "
        f"tick's frames of a connection in one `frames` message), "
        + (f"`--cpu-latency {args.cpu_latency}` (the daemon holds a PM QoS request: idle CPUs poll), "
           if args.cpu_latency is not None else "")
        + (f"`--realtime {args.realtime}` (the daemon's serving threads run SCHED_RR), " if args.realtime else "")
        + f"a fresh daemon per repeat; medians over {args.repeats} repeats, p99 range in brackets; "
        f"served/offered/degraded/dropped summed over repeats). Round trip = client send to client receive, "
        f"ZeroMQ DEALER -> ROUTER on loopback, ms. Wait: `sleep` = daemon and client sleep in poll between "
        f"messages; `busy` = `--busy-poll {BUSY_POLL_MS:g}` (the daemon's busy_poll_ms and the client both spin, "
        f"one core each). Take: CMU 07_01 on a loop with gaps-protocol dropouts. "
        f"Daemon budget 4 ms (lacuna bench default). Models trained on {', '.join(TRAIN)}. "
        f"Python {platform.python_version()}; load average at the end {' '.join(load)} (other sessions were "
        f"using the same 2 cores).",
        "",
        table(rows, args.repeats, args.seconds),
        "",
        "Counts agreed with the daemon's `status` in every run: "
        + ("yes" if all(r[k]["counts_agree"] for r in rows for k in ("model", "floor")) else "NO (see JSON)") + ".",
        f"Per-run JSON and histograms: `{Path(args.out).name}/` (not committed).",
        *([args.note] if args.note else []),
    ])
    if args.no_write:
        print(text)
    else:
        write_section(text)
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
