"""Read/write speed of the motion formats on real files (median and p90 over repeats).

Reproduce:  .venv/bin/python bench/formats_io.py [--repeats 20]
Needs the data directory ($LACUNA_DATA or ../shared/data).  Prints a Markdown table.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mocap.datasets import data_dir
from mocap.io import read_motion, write_motion


def _time(fn, repeats: int) -> tuple[float, float]:
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts)), float(np.percentile(ts, 90))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args()
    root = data_dir(required=True)
    cases = [root / "cmu" / "07" / "07_01.amc", root / "cmu" / "35" / "35_17.amc", root / "bvh" / "07_01.bvh"]
    print("| file | frames x channels | read median / p90 (ms) | write median / p90 (ms) | read per frame (us) |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for src in cases:
            m = read_motion(src)
            rows = [(src.name, src, m)]
            csv = Path(tmp) / (src.stem + ".csv")
            write_motion(csv, m)
            rows.append((f"{src.stem}.csv (from {src.suffix[1:].upper()})", csv, read_motion(csv)))
            for name, path, mm in rows:
                r = _time(lambda: read_motion(path), args.repeats)
                out = Path(tmp) / ("out" + path.suffix)
                w = _time(lambda: write_motion(out, mm), args.repeats)
                print(f"| {name} | {mm.n_frames} x {len(mm.channels)} | {r[0] * 1e3:.1f} / {r[1] * 1e3:.1f} "
                      f"| {w[0] * 1e3:.1f} / {w[1] * 1e3:.1f} | {r[0] / mm.n_frames * 1e6:.0f} |")
                print(f"done {name}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
