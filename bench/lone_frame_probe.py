"""One pass-through stream at 120 Hz through a real ``lacuna serve``: where a lone frame's daemon time
goes (issue 19, bench/notebook/spin-38.md).

Starts a daemon (the built-in pass-through, budget 4 ms, ``--daemon KEY=VALUE`` for other ``[daemon]``
settings, e.g. ``prewarm_spin_ms=0``), warms it for 2 s, then drives it with clients.loadgen for
``--seconds`` (56 random channels, every frame with its observed mask) and prints the round trip,
the daemon's own time per frame (``proc_us``) and ``status``'s ``prewarm`` counters (rehearsals, spins
and those a frame ended).  ``--py-spy OUT`` also samples the serving thread while it holds the GIL
(py-spy ``--gil --rate 3000``, raw format; py-spy is not a dependency: ``pip install py-spy``) and
prints the 20 leaf lines it found most often.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/lone_frame_probe.py [--daemon prewarm_spin_ms=0] [--py-spy /tmp/spy.txt]
"""
from __future__ import annotations

import argparse
import collections
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from clients.configfile import loopback_config  # noqa: E402
from clients.control import control  # noqa: E402
from clients.harness import DaemonProcess  # noqa: E402
from clients.loadgen import run_load  # noqa: E402


def leaves(raw: str, top: int = 20) -> list[tuple[int, str]]:
    """py-spy's raw output (``stack count`` lines): the most frequent (caller; leaf) pairs."""
    c: collections.Counter[str] = collections.Counter()
    for line in Path(raw).read_text().splitlines():
        stack, n = line.rsplit(" ", 1)
        c[";".join(stack.split(";")[-2:])] += int(n)
    return [(n, k) for k, n in c.most_common(top)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=9.0)
    ap.add_argument("--daemon", action="append", default=[], metavar="KEY=VALUE",
                    help="a [daemon] setting (a number), repeatable")
    ap.add_argument("--py-spy", dest="spy", metavar="OUT")
    args = ap.parse_args(argv)
    extra = {k: float(v) for k, v in (s.split("=", 1) for s in args.daemon)}
    d = tempfile.mkdtemp(prefix="lone-frame-")
    loopback_config(f"{d}/c.toml", {"floor": {"builtin": "passthrough"}},
                    daemon={"budget_ms": 4.0, "log_level": "warning", **extra})
    p = DaemonProcess(f"{d}/c.toml")
    p.start()
    try:
        ch = [f"c{i}" for i in range(56)]
        frames = np.random.default_rng(0).normal(size=(600, 56)).astype(np.float32)
        run_load(p.endpoints["router"], ch, frames, n_streams=1, rate=120, seconds=2, progress=False, prefix="warm")
        spy = None
        if args.spy:
            spy = subprocess.Popen([str(Path(sys.executable).parent / "py-spy"), "record", "--pid", str(p.proc.pid),
                                    "--rate", "3000", "--format", "raw", "-o", args.spy, "--duration",
                                    str(int(args.seconds + 1)), "--nonblocking", "--gil"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            time.sleep(1.0)
        r = run_load(p.endpoints["router"], ch, frames, n_streams=1, rate=120, seconds=args.seconds, progress=False)
        info = control(p.endpoints["router"], "status", timeout_s=5.0).result["prewarm"]
        if spy is not None:
            spy.wait(60)
    finally:
        p.proc.kill()
        p.proc.wait(10)
    s = r.summary()
    print(json.dumps({"daemon": extra, "round_trip": {k: s[k] for k in ("p50_ms", "p99_ms")},
                      "proc_ms": {"p50": s["daemon_proc_p50_ms"], "p99": s["daemon_proc_p99_ms"]},
                      "served": s["served"], "sent": s["sent"], "prewarm": info}, indent=1))
    if args.spy:
        for n, k in leaves(args.spy):
            print(f"{n:6d} {k}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
