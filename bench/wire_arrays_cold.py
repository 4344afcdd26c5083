"""A bundle read through its sender's layout against the msgpack way, warm and 8 ms after the last
call (a live tick's condition), us a frame of a 64-frame bundle, medians over the bundles, the ways
alternating bundle by bundle (issue 19; bench/NOTEBOOK.md, stop 41): ``unpack`` + ``decode_map``
(msgpack, then daemon/block.py's ``read_block``) against ``daemon.layout.Layouts.read`` (the
sender's layout learned from the first bundle).  (At commit 3665c84 this also timed the fills
written from arrays, daemon/rowpack.py, which did not pay cold and was reverted.)

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/wire_arrays_cold.py [--streams 64] [--channels 62] [--bundles 300]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402

from daemon import layout, wire  # noqa: E402
from daemon.decode import decode_map, unpack  # noqa: E402
from daemon.schema import Bundle, Frame  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--streams", type=int, default=64)
    ap.add_argument("--channels", type=int, default=62)
    ap.add_argument("--bundles", type=int, default=300)
    a = ap.parse_args()
    n, C, B = a.streams, a.channels, a.bundles
    rng = np.random.default_rng(0)
    sids = [f"p{i}" for i in range(n)]
    msgs = []
    for k in range(B + 1):
        ang = rng.standard_normal((n, C)).astype(np.float32)
        ang[:, :7] = np.nan  # (an arm missing)
        msgs.append(wire.encode(Bundle([Frame(s, 1000 + k, (1000 + k) / 120, ang[i]) for i, s in enumerate(sids)])))
    lays = layout.Layouts()
    assert lays.learn(msgs[0], unpack(msgs[0]), "w")
    ways = {"decode: msgpack + read_block": (lambda i: decode_map(unpack(msgs[i + 1])), B),
            "decode: Layouts.read": (lambda i: lays.read(msgs[i + 1], "w"), B)}
    print(f"{n} frames of {C} channels a bundle, {B} bundles, us a frame (median), ways alternating")
    for gap in (0.0, 0.008):
        ts: dict[str, list[float]] = {w: [] for w in ways}
        for i in range(B):
            for w, (fn, _) in ways.items():
                if gap:
                    time.sleep(gap)
                t0 = time.perf_counter()
                fn(i)
                ts[w].append(time.perf_counter() - t0)
        label = "warm" if not gap else f"{gap * 1e3:g} ms after the last call"
        print(f"  {label}:")
        for w, v in ts.items():
            print(f"    {w:32s} {np.median(v) * 1e6 / n:6.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
