"""daemon/rowpack.py writes each row's fill map as the very bytes msgpack packs the map to."""
from __future__ import annotations

import msgpack
import numpy as np
import pytest

from daemon import wire
from daemon.rowpack import fill_rows

PACK = msgpack.Packer(use_bin_type=True).pack


def _maps(sids, seqs, stamps, ang, fil, std, sts, model, proc_us, sty, ph):
    out = []
    for i in range(len(sids)):
        m = {"v": 1, "type": "fill", "stream": sids[i], "seq": seqs[i], "t": stamps[i], "angles": ang[i].tobytes(),
             "filled": fil[i].tobytes(), "std": std[i].tobytes(), "status": sts if isinstance(sts, str) else sts[i],
             "model": model, "proc_us": proc_us}
        if sty is not None:
            m["style"], m["phase"] = sty[i].tobytes(), float(ph[i])
        out.append(m)
    return out


@pytest.mark.parametrize("n, C, K", [(1, 1, None), (64, 62, 2), (5, 300, None), (3, 40, 7), (200, 17, 3), (2, 1024, 1)])
def test_rows_are_the_bytes_of_the_maps(n, C, K):
    rng = np.random.default_rng(n * 7 + C)
    ang = rng.normal(scale=100, size=(n, C)).astype(np.float32)
    ang[rng.random((n, C)) < 0.1] = np.nan
    std = rng.random((n, C)).astype(np.float32)
    fil = rng.random((n, C)) < 0.2
    # stream ids of every msgpack str width (fixstr, str8) and non-ASCII; seqs of every int width
    sids = [("s" * (1 + (i * 13) % 120)) + ("é" if i % 3 == 0 else "") for i in range(n)]
    seqs = [int(x) for x in rng.choice([0, 1, 127, 128, 255, 256, 65535, 65536, 2**32, 2**63 - 1], n)]
    stamps = [float(x) for x in rng.normal(scale=1e6, size=n)]
    sts = [["ok", "degraded", "passthrough"][i % 3] for i in range(n)] if n > 2 else "passthrough"
    sty = None if K is None else rng.random((n, K)).astype(np.float32)
    ph = None if K is None else list(rng.random(n) * 2 * np.pi)
    for model, proc_us in (("hlm", 0), ("a-much-longer-model-name-than-thirty-one-bytes", 2**40)):
        rows = fill_rows(sids, seqs, stamps, ang, fil, std, sts, model, proc_us, sty, ph)
        maps = _maps(sids, seqs, stamps, ang, fil, std, sts, model, proc_us, sty, ph)
        assert rows == [PACK(m) for m in maps]
        # and joined into one replies message, what the client reads back
        got = wire.decode(wire.join_replies(rows))
        assert isinstance(got, wire.Replies) and [f.stream for f in got.items] == sids


def test_a_subset_of_rows_in_any_order_is_still_each_rows_map():
    rng = np.random.default_rng(3)
    n, C = 10, 8
    ang = rng.normal(size=(n, C)).astype(np.float32)
    std = rng.random((n, C)).astype(np.float32)
    fil = rng.random((n, C)) < 0.5
    sel = [7, 2, 9]
    sids, seqs, stamps = [f"p{i}" for i in sel], sel, [i / 120 for i in sel]
    rows = fill_rows(sids, seqs, stamps, ang[sel], fil[sel], std[sel], "ok", "m", 5)  # (fancy-indexed: copies)
    rows_t = fill_rows(sids, seqs, stamps, ang.T.copy().T[sel], fil[sel], std[sel], "ok", "m", 5)  # (F-order input)
    assert rows == rows_t == [PACK(m) for m in _maps(sids, seqs, stamps, ang[sel], fil[sel], std[sel], "ok", "m", 5,
                                                       None, None)]
