"""The masked frame's finiteness check (daemon/decode.py ``well_formed``), cold, two ways alternating.

A lone frame's daemon time was ~0.2 ms at p50 on the 2-core VM (issue 19), and py-spy (``--gil``,
3000 Hz, one pass-through stream at 120 Hz) put 12% of the serving thread's time on one line: the
check that every observed value of a masked frame is finite, a numpy reduction with ``where=`` and a
float64 accumulator.  This times that line against the same test done by CPython alone (the
observed values picked by ``itertools.compress`` from a float32 ``memoryview``, summed in
double), each call after a sleep of ``--gap-ms`` as the live daemon waits between frames, the two
ways alternating call by call; medians and percentiles of per-call wall time.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/finite_cold.py --calls 400 --gap-ms 8 [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from itertools import compress

import numpy as np

_ADD = np.add.reduce


def numpy_way(angles: np.ndarray, observed: np.ndarray, b: bytes, ob: bytes) -> bool:
    return math.isfinite(_ADD(angles, where=observed, dtype=np.float64))


def cpython_way(angles: np.ndarray, observed: np.ndarray, b: bytes, ob: bytes) -> bool:
    return math.isfinite(sum(compress(memoryview(b).cast("f"), ob)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--calls", type=int, default=400)
    ap.add_argument("--gap-ms", type=float, default=8.0)
    ap.add_argument("--channels", type=int, default=56)
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    a = rng.normal(size=args.channels).astype(np.float32)
    miss = rng.choice(args.channels, 4, replace=False)
    a[miss] = np.nan
    ob = np.ones(args.channels, bool)
    ob[miss] = False
    b, obb = a.tobytes(), ob.tobytes()
    ways = {"numpy": numpy_way, "cpython": cpython_way}
    for f in ways.values():
        assert f(a, ob, b, obb)
    times: dict[str, list[float]] = {k: [] for k in ways}
    for i in range(args.calls):
        for k in (list(ways) if i % 2 == 0 else list(ways)[::-1]):
            time.sleep(args.gap_ms / 1000.0)
            t0 = time.perf_counter()
            ways[k](a, ob, b, obb)
            times[k].append(time.perf_counter() - t0)
    out = {"command": "python bench/finite_cold.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "at": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "loadavg": os.getloadavg(), "rows": {}}
    for k, v in times.items():
        us = np.array(v) * 1e6
        row = {"p50_us": float(np.median(us)), "p90_us": float(np.percentile(us, 90)),
               "p99_us": float(np.percentile(us, 99)), "calls": len(us)}
        out["rows"][k] = row
        print(f"{k:8s} p50 {row['p50_us']:.2f} us, p90 {row['p90_us']:.2f}, p99 {row['p99_us']:.2f} ({len(us)} calls, "
              f"{args.gap_ms} ms apart)")
    print(f"cpython / numpy, p50: {out['rows']['cpython']['p50_us'] / out['rows']['numpy']['p50_us']:.2f}")
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump(out, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
