"""64 performers x 120 Hz bundled through a real ``lacuna serve``: why frames are dropped, and (optionally)
where the serving thread spends its time (issue 19; bench/NOTEBOOK.md, "stop 39").

Starts a daemon serving MODEL (an HLM or ``default`` file, or ``floor`` for the built-in pass-through;
budget 4 ms, overdue = "drop", as bench/echo_vs_daemon.py's bundled case), warms it for 2 s, then drives it
with clients.loadgen for ``--seconds`` (CMU 35_08 with the left arm missing, bench/echo_vs_daemon.py's
frames; 64 streams in one ``frames`` message a tick on one connection) and prints the round trip, the
client's drop reasons and the daemon's own counters over the run (``status``: ``overdue_after_step`` = the
step ran but its answers would have left after the budget; ``dropped_overdue`` all overdue drops).
``--py-spy OUT`` also samples the serving thread while it holds the GIL (py-spy ``--gil --rate 2000``,
raw format; py-spy is not a dependency: ``pip install py-spy``) and prints the functions that were on
the stack in the largest share of samples.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bundled_probe.py MODEL.npz|floor [--seconds 10] [--py-spy /tmp/spy.txt]
"""
from __future__ import annotations

import argparse
import collections
import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.echo_vs_daemon import MISSING, TEST, TRAIN  # noqa: E402
from clients.configfile import loopback_config  # noqa: E402
from clients.control import control  # noqa: E402
from clients.harness import DaemonProcess  # noqa: E402
from clients.loadgen import run_load  # noqa: E402


def inclusive(raw: str, top: int = 30) -> tuple[int, list[tuple[float, str]]]:
    """py-spy's raw output: (samples, the ``top`` functions by the share of samples they were on the stack)."""
    total, c = 0, collections.Counter[str]()
    for line in Path(raw).read_text().splitlines():
        stack, n = line.rsplit(" ", 1)
        total += int(n)
        seen = {re.sub(r":\d+\)$", ")", re.sub(r"\(/.*/", "(", f)) for f in stack.split(";")}
        for f in seen:
            c[f] += int(n)
    return total, [(100.0 * n / max(1, total), k) for k, n in c.most_common(top)]


def counters(st: dict[str, Any]) -> dict[str, int]:
    return {k: int(v) for k, v in st.get("counters", {}).items() if isinstance(v, (int, float))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model", help="a model file, or floor (the built-in pass-through)")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--py-spy", dest="spy", metavar="OUT")
    ap.add_argument("--pub", action="store_true", help="also a PUB socket (each fill published: a studio's downstream)")
    args = ap.parse_args(argv)
    from mocap.datasets import load_trial

    test = load_trial(TEST)
    channels = list(load_trial(TRAIN[0]).channels)
    frames = test.frames[:, test.index(channels)].astype(np.float32)
    observed = np.broadcast_to(~np.array([c.split(".")[0] in MISSING for c in channels]), frames.shape).copy()
    spec = {"builtin": "passthrough", "channels": channels} if args.model == "floor" else {"file": args.model}
    d = tempfile.mkdtemp(prefix="bundled-probe-")
    # ROUTER only, as bench/echo_vs_daemon.py's daemons (--pub adds a PUB socket: every fill published too)
    loopback_config(f"{d}/c.toml", {"m": spec}, pub=args.pub, daemon={"budget_ms": 4.0, "log_level": "warning"})
    p = DaemonProcess(f"{d}/c.toml")
    p.start()
    load = dict(n_streams=64, rate=120, progress=False, connections=1, bundle=True)
    try:
        run_load(p.endpoints["router"], channels, frames, observed, seconds=2, prefix="warm", **load)
        before = counters(control(p.endpoints["router"], "status", timeout_s=5.0).result)
        spy = None
        if args.spy:
            spy = subprocess.Popen([str(Path(sys.executable).parent / "py-spy"), "record", "--pid", str(p.pid),
                                    "--rate", "2000", "--format", "raw", "-o", args.spy, "--duration",
                                    str(int(args.seconds + 1)), "--nonblocking", "--gil"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            time.sleep(1.0)
        r = run_load(p.endpoints["router"], channels, frames, observed, seconds=args.seconds, **load)
        after = counters(control(p.endpoints["router"], "status", timeout_s=5.0).result)
        if spy is not None:
            spy.wait(60)
    finally:
        p.stop()
    s = r.summary()
    moved = {k: v - before.get(k, 0) for k, v in after.items()
             if v != before.get(k, 0) and any(w in k for w in ("overdue", "dropped", "over_budget", "frames"))}
    print(json.dumps({"model": args.model, "round_trip_ms": {k: s[k] for k in ("p50_ms", "p99_ms")},
                      "sent": s["sent"], "served": s["served"], "client_drop_reasons": r.drop_reasons,
                      "daemon_counters": moved}, indent=1))
    if args.spy:
        total, rows = inclusive(args.spy)
        print(f"py-spy: {total} samples with the GIL held")
        for share, k in rows:
            print(f"{share:5.1f}% {k}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
