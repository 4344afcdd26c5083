"""CPU cost of one rejected message in the daemon, with and without the rejection log limit.

Feeds seeded malformed messages (tests/fuzzgen.py, the fuzz test's generator) through the real
``Daemon._handle`` (daemon/loop.py) (decode -> reject -> count -> log -> error answer encoded), its transport
replaced by a list and its JSON log written to /dev/null as it would be to a pipe.  Compares
the daemon as built (``dispatch.REJECT_LOG_PER_S`` rejection lines a second, the rest counted)
with the limit lifted (one JSON line per rejection, as before the limit).  Process CPU time per
message, medians over repeats, both variants interleaved so machine load hits them alike.

    .venv/bin/python bench/reliability_reject_cost.py --repeats 7 --json bench/reliability_reject_cost.json
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from daemon import config, dispatch, wire
from daemon.log import Log
from daemon.loop import Daemon

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import fuzzgen  # noqa: E402

LIMIT = dispatch.REJECT_LOG_PER_S


def measure(d: Daemon, msgs: list[tuple[bytes, tuple]], limited: bool) -> float:
    dispatch.REJECT_LOG_PER_S = LIMIT if limited else 1 << 62  # read on every rejection
    c0 = time.process_time()
    for data, origin in msgs:
        d._handle(data, origin, time.perf_counter())
    return 1e6 * (time.process_time() - c0) / len(msgs)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--messages", type=int, default=20000)
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args(argv)
    cfg = config.from_dict({"daemon": {"max_message_bytes": 4096},
                            "models": {"floor": {"builtin": "passthrough", "channels": [f"c{i}" for i in range(62)]}}})
    devnull = open(os.devnull, "w")
    d = Daemon(cfg, Log("info", devnull))
    sent: list[int] = []
    d._send = lambda o, m, publish=False: sent.append(len(wire.encode(m)))  # type: ignore[method-assign]
    gen = fuzzgen.Fuzz(1234, 62, 4096, ["s1", "s2"])
    half = args.messages // 2
    msgs = [(b, ("router", [b"peer"])) for b, *_ in gen.zmq_batch(half)] + \
           [(b, ("osc", ("127.0.0.1", 9))) for b, *_ in gen.osc_batch(args.messages - half)]
    runs: dict[str, list[float]] = {"limited": [], "every_line": []}
    for i in range(args.repeats):
        for variant in (("limited", "every_line") if i % 2 == 0 else ("every_line", "limited")):
            runs[variant].append(measure(d, msgs, variant == "limited"))
        print(f"repeat {i + 1}/{args.repeats}: limited {runs['limited'][-1]:.1f} us, every line "
              f"{runs['every_line'][-1]:.1f} us per rejected message", file=sys.stderr, flush=True)
    med = {k: float(np.median(v)) for k, v in runs.items()}
    out = {"us_cpu_per_rejected_message_median": med, "runs": runs, "messages": len(msgs),
           "rejected": d.metrics.counters.get("rejected", 0)}
    if args.json_out:
        Path(args.json_out).write_text(json.dumps(out, indent=1) + "\n")
    print(f"CPU per rejected message (median of {args.repeats}): limited log {med['limited']:.1f} us, "
          f"one line per rejection {med['every_line']:.1f} us ({med['every_line'] / med['limited']:.2f}x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
