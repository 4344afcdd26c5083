"""What one frame costs the daemon after it has waited, and what a rehearsal before it takes back.

In process (no sockets), through the real Daemon object (decode -> session -> plan and step ->
fill message -> encode), one stream of the pan2009 held-out walk with the left arm and the head
missing, for the pass-through filler and each ``--model``:

- **after a gap**: the frame's wall time after the thread spun for G ms doing nothing (G = 0 ...
  8): how fast what the CPU cached of the daemon decays while the machine does other work;
- **sleep or spin**: after 8 ms spent sleeping, against 8 ms spent spinning: whether the cost
  after a wait comes from the thread being woken or from the time that passed;
- **rehearsed**: after 8 ms of which the last ``--lead`` ms follow a rehearsal of the previous
  frame (``daemon.prewarm``, what ``prewarm_ms`` does before a frame is due).

The cases alternate frame by frame, so a busy spell of the shared machine falls on all of them.
Median, p90 and p99 per case; JSON and a PNG plot.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/cold_decay.py --model hlm=bench/out/hlm.npz [--cpu-latency 0] [--rounds 150] [--json OUT] [--plot OUT.png]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from daemon import config, wire  # noqa: E402
from daemon.models import load_all  # noqa: E402
from daemon.pmqos import CpuLatency  # noqa: E402
from daemon.server import Daemon  # noqa: E402
from mocap.protocols import get_protocol  # noqa: E402

GAPS_MS = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
WAIT_MS = 8.0
SKIP = 10  # first rounds not counted


def _spin(ms: float) -> None:
    end = time.perf_counter() + ms / 1000.0
    while time.perf_counter() < end:
        pass


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", action="append", default=[], metavar="NAME=FILE")
    ap.add_argument("--rounds", type=int, default=150)
    ap.add_argument("--lead", type=float, default=1.0, help="ms between the rehearsal and the frame (default 1)")
    ap.add_argument("--cpu-latency", type=int, default=None, metavar="US")
    ap.add_argument("--json", dest="json_out")
    ap.add_argument("--plot", dest="plot_out")
    args = ap.parse_args(argv)
    qos = CpuLatency()
    if args.cpu_latency is not None and not qos.request(args.cpu_latency):
        raise SystemExit(f"--cpu-latency: {qos.error}")
    proto = get_protocol("pan2009")
    ch = list(proto.training_set().channels)
    frames = proto.cases()[0].truth.astype(np.float32)
    frames[:, [c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "head") for c in ch]] = np.nan
    models = {"floor": {"builtin": "passthrough"}, **{s.split("=", 1)[0]: {"file": s.split("=", 1)[1]} for s in args.model}}
    cfg = config.from_dict({"daemon": {"budget_ms": 1000.0, "log_level": "warning", "overdue": "serve", "prewarm_ms": 0.5},
                            "models": models, "zmq": {"router": "tcp://127.0.0.1:*"}})
    d = Daemon(cfg)
    table, errors = load_all(cfg)
    assert not errors, errors
    d._install(table)
    d._send = lambda o, m, publish=False: wire.encode(m)  # type: ignore[method-assign]
    cases = [f"spin {g:g} ms" for g in GAPS_MS] + [f"sleep {WAIT_MS:g} ms", f"spin {WAIT_MS:g} ms, rehearsed {args.lead:g} ms before"]
    rows = []
    try:
        for name in models:
            sid = f"s-{name}"
            d._handle(wire.encode(wire.Hello(sid, ch, name)), ("router", [b"x"]), time.perf_counter())
            times: dict[str, list[float]] = {c: [] for c in cases}
            k = 0
            for r in range(args.rounds):
                for c in cases:
                    if c.startswith("sleep"):
                        time.sleep(WAIT_MS / 1000.0)
                    elif "rehearsed" in c:
                        _spin(WAIT_MS - args.lead)
                        d.prewarm.rehearse(d.sessions.sessions, d.sched, wire.encode)
                        _spin(args.lead)
                    else:
                        _spin(float(c.split()[1]))
                    msg = wire.encode(wire.Frame(sid, k, k / 120, frames[k % len(frames)]))
                    t0 = time.perf_counter()
                    d._handle(msg, ("router", [b"x"]), t0)
                    d._serve()
                    times[c].append(time.perf_counter() - t0)
                    k += 1
                if r % 50 == 49:
                    print(f"{name}: {r + 1}/{args.rounds} rounds", file=sys.stderr, flush=True)
            for c in cases:
                q = np.percentile(np.array(times[c][SKIP:]) * 1e6, [50, 90, 99])
                rows.append({"model": name, "case": c, "us_p50": round(float(q[0]), 1), "us_p90": round(float(q[1]), 1),
                             "us_p99": round(float(q[2]), 1)})
                print(f"{name:>6}  {c:<34} p50 {q[0]:7.1f}  p90 {q[1]:7.1f}  p99 {q[2]:7.1f} us", flush=True)
            d.sessions.reset(sid)
    finally:
        qos.release()
    out = {"command": "python bench/cold_decay.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "rounds": args.rounds, "lead_ms": args.lead, "cpu_latency_us": args.cpu_latency, "rows": rows}
    if args.json_out:
        Path(args.json_out).write_text(json.dumps(out, indent=1))
    if args.plot_out:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 4))
        for name in models:
            got = {r["case"]: r for r in rows if r["model"] == name}
            line = ax.plot(GAPS_MS, [got[f"spin {g:g} ms"]["us_p50"] for g in GAPS_MS], marker="o", label=f"{name}: after a gap (p50)")
            col = line[0].get_color()
            ax.plot(GAPS_MS, [got[f"spin {g:g} ms"]["us_p99"] for g in GAPS_MS], ls=":", color=col, label=f"{name}: p99")
            reh = got[f"spin {WAIT_MS:g} ms, rehearsed {args.lead:g} ms before"]
            ax.plot([WAIT_MS], [reh["us_p50"]], marker="*", ms=14, ls="", color=col, label=f"{name}: 8 ms, rehearsed (p50)")
        ax.set_xlabel("ms since the previous frame (spinning)")
        ax.set_ylabel("us for one frame, in process")
        ax.set_title("The daemon's cost for a frame after a wait")
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(args.plot_out, dpi=110)
    return 0


if __name__ == "__main__":
    sys.exit(main())
