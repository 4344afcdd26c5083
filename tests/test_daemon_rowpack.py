"""A bundle's fills written from arrays by one compiled call (daemon/rowpack.py): each row the
very bytes msgpack packs its fill map to, on fuzzed rows; and a real ROUTER's held answers, rows
and maps mixed and more than one ``replies`` can hold, leave as the same messages as the maps
alone would."""
from __future__ import annotations

import time

import msgpack
import numpy as np
import pytest
import zmq

from daemon import config, rowpack, wire
from daemon.metrics import Metrics
from daemon.transport import Transports

pytestmark = pytest.mark.skipif(not rowpack.jit.enabled(), reason="rows are written by compiled code (LACUNA_NO_JIT=1 turns them off)")


def _case(rng, n, C=None):
    C, K = C or int(rng.choice([1, 5, 62, 63, 64, 65, 100])), int(rng.choice([0, 2, 5]))
    full = bool(rng.random() < 0.5)
    return dict(
        sids=[("s" * int(rng.integers(1, 40))) + str(i) for i in range(n)],
        seqs=[int(rng.choice([0, 5, 127, 128, 255, 256, 65535, 65536, 2**32 - 1, 2**32, 2**63 - 1])) for _ in range(n)],
        stamps=[float(rng.normal() * 1e3) for _ in range(n)],
        angles=rng.normal(size=(n, C)).astype(np.float32),
        filled=(rng.random((n, C)) > 0.5) if full else None,
        std=np.abs(rng.normal(size=(n, C))).astype(np.float32) if full else None,
        statuses=[str(rng.choice(["ok", "degraded", "passthrough"])) for _ in range(n)] if rng.random() < 0.5 else None,
        status="passthrough", model=str(rng.choice(["pt", "hlm-walk"])), proc_us=int(rng.choice([0, 5, 200, 70000, -3])),
        style=rng.random((n, K)).astype(np.float32) if K else None,
        phases=[float(x) for x in rng.random(n)] if rng.random() < 0.5 else None,
        gaps=[int(rng.choice([0, 0, 1, 3, 300])) for _ in range(n)] if rng.random() < 0.5 else None)


def _maps(c):
    out = []
    for i, sid in enumerate(c["sids"]):
        C = c["angles"].shape[1]
        m = {"v": 1, "type": "fill", "stream": sid, "seq": c["seqs"][i], "t": c["stamps"][i], "angles": c["angles"][i].tobytes(),
             "filled": bytes(C) if c["filled"] is None else c["filled"][i].tobytes(),
             "std": bytes(4 * C) if c["std"] is None else c["std"][i].tobytes(),
             "status": c["status"] if c["statuses"] is None else c["statuses"][i], "model": c["model"], "proc_us": c["proc_us"]}
        if c["style"] is not None:
            m["style"] = c["style"][i].tobytes()
        if c["phases"] is not None:
            m["phase"] = c["phases"][i]
        if c["gaps"] is not None and c["gaps"][i] > 0:
            m["gap"] = c["gaps"][i]
        out.append(m)
    return out


@pytest.mark.parametrize("seed", range(4))
def test_each_row_is_msgpacks_bytes_of_its_fill_map(seed):
    rng = np.random.default_rng(seed)
    rp = rowpack.RowPack()
    for _ in range(60):
        c = _case(rng, int(rng.integers(1, 20)))
        rows = rp.encode(**c)
        maps = _maps(c)
        assert len(rows) == len(maps) and rows.sids == c["sids"]
        for i, m in enumerate(maps):
            assert rows.row(i) == msgpack.packb(m, use_bin_type=True)
        assert rows.data == b"".join(msgpack.packb(m, use_bin_type=True) for m in maps)
    assert len(rowpack._rows_kernel.signatures) == 1  # (compiled once, at start, with the types a tick gives it)


def test_held_rows_and_maps_leave_as_the_maps_alone_would():
    """Over a real ROUTER: a peer's held answers, a map, 1,500 rows (more than one ``replies``
    holds) and another map, flushed, arrive as the messages the same answers as maps give."""
    cfg = config.from_dict({"daemon": {"log_level": "error"}, "models": {"pt": {"builtin": "passthrough"}},
                            "zmq": {"router": "tcp://127.0.0.1:*"}})
    net = Transports(cfg, lambda *a: None, lambda *a, **k: None, Metrics(), lambda *a, **k: None)
    net.open()
    got: list[tuple] = []
    net.on_batch = got.extend
    ctx = zmq.Context()  # (its own, ended below: the process keeps no ZeroMQ I/O thread after the test)
    peer = ctx.socket(zmq.DEALER)
    peer.setsockopt(zmq.LINGER, 0)
    try:
        peer.connect(net.endpoints()["router"])
        peer.send(b"hello")
        deadline = time.monotonic() + 10
        while not got and time.monotonic() < deadline:
            net.receive(net.poll(100))
        assert got
        origin = (*got[0][1], "bundle")
        rng = np.random.default_rng(7)
        c = _case(rng, 1500, C=8)  # (small: the two replies stay under the decoder's size cap)
        rows = rowpack.RowPack().encode(**c)
        first, last = wire.Drop("x", 1, "conflated"), wire.Drop("y", 2, "overdue")

        def received(answers=1502):  # (the messages that carry the flushed answers, read until all have come)
            out, n = [], 0
            while n < answers:
                assert peer.poll(10000), f"{n} of {answers} answers came"
                out.append(peer.recv())
                n += len(wire.decode(out[-1]).items)
            return out

        net.hold()
        net.send(origin, first)
        net.send_fill_rows(origin, rows)
        net.send(origin, last)
        assert net.flush() == 1502
        with_rows = received()
        net.hold()
        net.send(origin, first)
        net.send_fill_maps(origin, _maps(c))
        net.send(origin, last)
        assert net.flush() == 1502
        with_maps = received()
        assert with_rows == with_maps and len(with_rows) == 2
        items = [m for b in with_rows for m in wire.decode(b).items]
        assert [type(m).__name__ for m in items] == ["Drop"] + ["FillMsg"] * 1500 + ["Drop"]
        assert [m.seq for m in items[1:-1]] == c["seqs"]
    finally:
        peer.close()
        ctx.term()
        net.close(0)
