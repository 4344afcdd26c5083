"""A bundle read through its sender's layout (daemon/layout.py) against the usual way (msgpack,
then daemon.block.read_block): the same block or none, on fuzzed bundles; two daemons, one
reading through layouts and one not, send the same bytes and end in the same state; and a real
daemon process reads a studio's bundles through their layout."""
from __future__ import annotations

import time

import msgpack
import numpy as np
import pytest
import zmq
from test_daemon_wire_block import PEER, FakeClock, StyledHold, _daemon

from clients.control import control
from clients.harness import DaemonProcess
from daemon import layout, wire
from daemon.block import read_block
from daemon.decode import unpack
from daemon.schema import F32, WireError

pytestmark = pytest.mark.skipif(not layout.jit.enabled(), reason="layouts are read by compiled code (LACUNA_NO_JIT=1 turns them off)")

BASES = [3, 130, 300, 70_000, 1 << 33, (1 << 63) - 5000]  # fixint, uint8, uint16, uint32, uint64 and next to MAX_SEQ


def _element(rng, sid, seq, t, C, masked, extra):
    a = rng.normal(scale=30, size=C).astype(np.float32)
    obs = rng.random(C) > 0.3
    d = {"stream": sid, "seq": seq, "t": t}
    if masked:
        a[~obs] = rng.choice([np.nan, np.inf, 7.0])
        d.update(angles=a.tobytes(), observed=obs.astype(np.uint8).tobytes())
    else:
        a[~obs] = np.nan
        d.update(angles=a.tobytes())
    if extra:
        d["note"] = "x"  # (an unknown key: ignored, and part of the layout)
    return d


def _bundle(els):
    return msgpack.packb({"v": 1, "type": "frames", "frames": els}, use_bin_type=True)


def _usual(data):
    try:
        m = unpack(data)
    except WireError:
        return None
    fr = m.get("frames")
    with np.errstate(invalid="ignore"):  # (inf - inf where observed: read_block refuses it, warning)
        return read_block(fr) if m.get("type") == "frames" and m.get("v") == 1 and type(fr) is list and fr else None


def _same(a, b):
    assert a.sids == b.sids and a.seqs == b.seqs
    assert np.array_equal(np.array(a.stamps).view(np.uint64), np.array(b.stamps).view(np.uint64))
    assert a.values.dtype == b.values.dtype == F32 and np.array_equal(a.values.view(np.uint32), b.values.view(np.uint32))
    assert (a.mask is None) == (b.mask is None)
    if a.mask is not None:
        assert a.mask.dtype == np.bool_ and np.array_equal(a.mask, b.mask)
    assert not a.values.flags.writeable


@pytest.mark.parametrize("seed", range(8))
def test_a_bundle_read_through_its_layout_is_the_block_msgpack_and_read_block_give(seed):
    rng = np.random.default_rng(seed)
    n, C = int(rng.integers(1, 12)), int(rng.integers(1, 80))
    masked, extra = bool(rng.random() < 0.5), bool(rng.random() < 0.3)
    base = BASES[seed % len(BASES)]
    sids = [("s" * int(rng.integers(1, 6))) + str(i) for i in range(n)]  # ids of several lengths

    def make(k, bad=0.0):
        els = [_element(rng, sid, base + k + int(rng.integers(0, 3)), float(1000 + k / 120), C, masked, extra) for sid in sids]
        if rng.random() < bad:  # a stamp that is not finite
            els[int(rng.integers(n))]["t"] = float(rng.choice([np.inf, -np.inf, np.nan]))
        if masked and rng.random() < bad:  # a mask byte other than 0 or 1
            e = els[int(rng.integers(n))]
            ob = bytearray(e["observed"])
            ob[int(rng.integers(C))] = 2
            e["observed"] = bytes(ob)
        if not masked and rng.random() < bad:  # an infinity where no mask says missing
            e = els[int(rng.integers(n))]
            a = np.frombuffer(e["angles"], F32).copy()
            a[int(rng.integers(C))] = np.inf
            e["angles"] = a.tobytes()
        return _bundle(els)

    lays, who = layout.Layouts(), ("conn", b"studio")
    first = make(0)
    assert lays.learn(first, unpack(first), who)
    assert not lays.learn(first, unpack(first), who)  # (learned once)
    served = refused = 0
    for k in range(1, 110):  # (seqs keep their width: base + 111 at most)
        data = make(k, bad=0.15)
        flip = rng.random() < 0.3
        if flip:  # any byte, structure or value
            b = bytearray(data)
            b[int(rng.integers(len(b)))] ^= int(rng.integers(1, 256))
            data = bytes(b)
        got, ref = lays.read(data, who), _usual(data)
        if got is not None:
            assert ref is not None
            _same(got, ref)
            served += 1
        elif not flip:
            assert ref is None  # only a value the usual way refuses too
            refused += 1
        assert lays.read(data, ("conn", b"other")) is None  # (another sender's layouts are its own)
    assert served > 40 and refused > 5
    assert len(layout._read_kernel.signatures) == 1  # (compiled once, at start: the live bytes' type is the one warmed)


def test_layouts_are_learned_only_from_bundles_they_can_read_again_exactly():
    lays, who, C = layout.Layouts(), ("conn", b"a"), 5
    rng = np.random.default_rng(0)

    def learn(els):
        data = _bundle(els)
        return lays.learn(data, unpack(data), who)

    assert not learn([{**_element(rng, "a", 255, 1.0, C, False, False), "seq": -1}])  # not a bundle read_block takes
    el = _element(rng, "b", 300, 1.0, C, False, False)
    data = _bundle([el])
    odd = data.replace(msgpack.packb(1.0), b"\xca" + np.array([1.0], ">f4").tobytes())  # t as float32: not canonical
    assert odd != data and not lays.learn(odd, unpack(odd), who)
    assert not learn([{**el, "angles": b"\0" * 4 * (C + 1)}, el])  # elements of two widths: not a regular bundle
    assert learn([el]) and lays.read(data, who) is not None
    lays.forget(who)
    assert lays.read(data, who) is None


def _steps(rng, sids, name, C, clock, start):
    """Turns of a studio sending bundles numbered from ``start`` (some masked, some with a frame
    missing, out of order, late, duplicated or malformed), a re-handshake now and then."""
    seqs = dict.fromkeys(sids, start)
    for k in range(80):
        now = clock.t + 1 / 120
        items = []
        if k == 0 or rng.random() < 0.03:
            for sid in (sids if k == 0 else [str(rng.choice(sids))]):
                items.append((wire.encode(wire.Hello(sid, [f"c{i}" for i in range(C)], name)), PEER, now))
        masked = bool(rng.random() < 0.3)
        els = []
        for sid in sids:
            seqs[sid] += int(rng.choice([1] * 90 + [2, 0, -1]))
            els.append(_element(rng, sid, seqs[sid], now - 0.001, C, masked, False))
        if rng.random() < 0.05:
            els[0]["angles"] = b"\0" * (4 * C + 4)
        items.append((_bundle(els), PEER, now - (0.0035 if rng.random() < 0.2 else 0.0)))
        yield items


@pytest.mark.parametrize("case", ["pt", "styled"])
@pytest.mark.parametrize("seed", range(3))
def test_a_daemon_reading_through_layouts_answers_as_one_that_does_not(case, seed):
    import test_daemon_wire_block as wb

    from daemon.layout import Layouts

    C = wb.C
    rng = np.random.default_rng(seed)
    clock = FakeClock()
    model = StyledHold([f"c{i}" for i in range(C)], np.zeros(C), np.ones(C)) if case == "styled" else None
    name = "st" if model is not None else "pt"
    fast, ref = (_daemon(clock, True, "drop", model) for _ in range(2))
    ref.layouts = Layouts()
    ref.layouts.on = False
    sids = [f"p{i}" for i in range(int(rng.integers(1, 9)))]
    for items in _steps(rng, sids, name, C, clock, [0, 100, 1000][seed]):  # (0, 100: seqs change width on the way)
        clock.t += 1 / 120
        for d in (fast, ref):
            d.sched.encode_cost, d.sched.send_cost = 20e-6, 40e-6
            d.turn(clock(), items=list(items))
        assert fast.sent == ref.sent
        a, b = wb._state(fast), wb._state(ref)
        a[1].pop("bundles_by_layout", None)
        assert a == b
        fast.sent.clear()
        ref.sent.clear()
    assert fast.layouts.hits > 30 and fast.metrics.counters["bundles_by_layout"] == fast.layouts.hits
    assert ref.layouts.hits == 0 and "bundles_by_layout" not in ref.metrics.counters


def test_a_live_daemon_reads_a_studios_bundles_through_their_layout(tmp_path):
    """A real daemon process and a real ZeroMQ DEALER: 4 streams' bundles numbered from 500, every
    frame answered with its fill; the status counts the bundles read through the layout."""
    C = 8
    d = DaemonProcess({"pt": {"builtin": "passthrough", "channels": [f"c{i}" for i in range(C)]}},
                      workdir=str(tmp_path / "d"), daemon={"budget_ms": 200.0})
    d.start()
    ctx = zmq.Context()  # (its own, ended below: the process keeps no ZeroMQ I/O thread after the test)
    s = ctx.socket(zmq.DEALER)
    s.setsockopt(zmq.LINGER, 0)
    s.connect(d.endpoint)
    try:
        sids = [f"actor{i}" for i in range(4)]
        for sid in sids:
            s.send(wire.encode(wire.Hello(sid, [f"c{i}" for i in range(C)], "pt")))
            assert s.poll(30000) and isinstance(wire.decode(s.recv()), wire.HelloAck)
        rng = np.random.default_rng(1)
        got: dict[str, list[int]] = {sid: [] for sid in sids}
        for k in range(40):
            s.send(_bundle([_element(rng, sid, 500 + k, time.time(), C, False, False) for sid in sids]))
            assert s.poll(30000), f"no answer to bundle {k}"
            rep = wire.decode(s.recv())
            for m in rep.items:
                assert isinstance(m, wire.FillMsg), m
                got[m.stream].append(m.seq)
        assert all(v == list(range(500, 540)) for v in got.values())
        counters = control(d.endpoint, "status").result["counters"]
        assert counters.get("bundles_by_layout", 0) >= 38 and counters["frames_out"] == 160, counters
    finally:
        s.close()
        ctx.term()
        d.stop()
