"""The wire's two compiled passes against the msgpack way, warm and 8 ms after the last call (a live
tick's condition), us a frame of a 64-frame bundle, medians over the bundles, the ways alternating
bundle by bundle (issue 19; bench/NOTEBOOK.md, stop 41):

* decode: ``unpack`` + ``decode_map`` (msgpack, then daemon/block.py's ``read_block``) against
  ``daemon.layout.Layouts.read`` (the sender's layout learned from the first bundle);
* encode: the HLM bundle's fill maps as daemon/tickblock.py builds them + ``replies_of`` against
  ``daemon.rowpack.RowPack.encode`` + ``replies_joined``.

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

import msgpack  # noqa: E402
import numpy as np  # noqa: E402

from daemon import layout, rowpack, wire  # noqa: E402
from daemon.decode import decode_map, unpack  # noqa: E402
from daemon.schema import Bundle, Frame  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--streams", type=int, default=64)
    ap.add_argument("--channels", type=int, default=62)
    ap.add_argument("--bundles", type=int, default=300)
    a = ap.parse_args()
    n, C, K, B = a.streams, a.channels, 2, a.bundles
    rng = np.random.default_rng(0)
    sids = [f"p{i}" for i in range(n)]
    msgs = []
    for k in range(B + 1):
        ang = rng.standard_normal((n, C)).astype(np.float32)
        ang[:, :7] = np.nan  # (an arm missing)
        msgs.append(wire.encode(Bundle([Frame(s, 1000 + k, (1000 + k) / 120, ang[i]) for i, s in enumerate(sids)])))
    lays = layout.Layouts()
    assert lays.learn(msgs[0], unpack(msgs[0]), "w")
    rp, pack = rowpack.RowPack(), msgpack.Packer(use_bin_type=True).pack
    ticks = [(rng.standard_normal((n, C)).astype(np.float32), np.abs(rng.standard_normal((n, C))).astype(np.float32),
              rng.random((n, C)) > 0.8, rng.random((n, K)).astype(np.float32), rng.random(n), [1000 + k] * n, [k / 120] * n)
             for k in range(B)]

    def maps_way(t):
        ang, std, filled, sty, ph, seqs, stamps = t
        ab, sb, fb, yb = ang.tobytes(), std.tobytes(), filled.tobytes(), sty.tobytes()
        k4, kk = 4 * C, 4 * K
        cols = zip(sids, seqs, stamps, [ab[i * k4:(i + 1) * k4] for i in range(n)], [fb[i * C:(i + 1) * C] for i in range(n)],
                   [sb[i * k4:(i + 1) * k4] for i in range(n)], [yb[i * kk:(i + 1) * kk] for i in range(n)], ph.tolist())
        maps = [{"v": 1, "type": "fill", "stream": s, "seq": q, "t": tt, "angles": x, "filled": f, "std": d, "status": "ok",
                 "model": "hlm", "proc_us": 1234, "style": y, "phase": p} for s, q, tt, x, f, d, y, p in cols]
        return wire.replies_of(maps, pack)

    def rows_way(t):
        ang, std, filled, sty, ph, seqs, stamps = t
        r = rp.encode(sids, seqs, stamps, ang, filled, std, None, "ok", "hlm", 1234, sty, ph, None)
        return wire.replies_joined(r.data, len(r))

    assert maps_way(ticks[0]) == rows_way(ticks[0])
    ways = {"decode: msgpack + read_block": (lambda i: decode_map(unpack(msgs[i + 1])), B),
            "decode: Layouts.read": (lambda i: lays.read(msgs[i + 1], "w"), B),
            "encode: maps + replies_of": (lambda i: maps_way(ticks[i]), B),
            "encode: RowPack.encode": (lambda i: rows_way(ticks[i]), B)}
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
