"""OSC bundles of frames on the array path (daemon/oscblock.py -> daemon/blockpath.py ->
daemon/tickblock.py) against the row path (python-osc's decoder element by element, a Frame and a
pending slot each, a FillMsg and osc.encode each), over real UDP sockets on loopback.

Two in-process daemons, the array path on and off, each with a real OSC socket: one client socket
sends both the same fuzzed turns (bundles of the studio's streams, in and out of order, cut short,
with gaps, duplicates and late frames, masked and not, hostile elements: malformed, infinite,
the wrong width, negative seqs, a hello or a nested bundle among the frames, truncated datagrams,
and an intruder's socket sending bundles of the studio's streams); the datagrams each daemon sends
back must be the same bytes in the same order, and every session, counter and cost estimate the
same.  The array path must have served (``block_served``).  One fake clock: no answer depends on
the machine's speed.  Also: :func:`daemon.oscblock.read` against :func:`daemon.osc.decode_bundle`
element for element, :func:`daemon.oscblock.fill_datagram` against :func:`daemon.osc.encode`, and
real CMU frames to a real daemon process."""
from __future__ import annotations

import select
import socket
import struct

import numpy as np
import pytest
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message import OscMessage
from pythonosc.osc_message_builder import OscMessageBuilder

from daemon import budget, config, osc, oscblock, server, wire
from daemon.models import Loaded, load_all
from daemon.pack import fill_map
from tests.test_daemon_wire_block import C, FakeClock, StyledHold, _state

MARK = b"#mark"


def _msg(addr, args):
    b = OscMessageBuilder(addr)
    for v, t in args:
        b.add_arg(v, t)
    return b.build().dgram


def _frame(sid, seq, t, vals, seqtag="i", ttag="d"):
    return _msg("/lacuna/frame", [(sid, "s"), (seq, seqtag), (t, ttag)] + [(float(v), "f") for v in vals])


def _masked(sid, seq, t, vals, obs):
    return _msg("/lacuna/frame/masked", [(sid, "s"), (seq, "i"), (t, "d"),
                                         (np.asarray(vals, np.float32).tobytes(), "b"), (obs.astype(np.uint8).tobytes(), "b")])


def _bundle(elements):
    return b"#bundle\0" + (1).to_bytes(8, "big") + b"".join(struct.pack(">i", len(e)) + e for e in elements)


def _hello(sid, model):
    return _msg("/lacuna/hello", [(sid, "s"), (model, "s")] + [(f"c{i}", "s") for i in range(C)])


def _values(rng, masked):
    a = rng.normal(scale=2, size=C).astype(np.float32)
    obs = rng.random(C) > 0.3
    if masked:
        a[~obs] = rng.choice([np.nan, 5.0])
    else:
        a[~obs] = np.nan
        if rng.random() < 0.05:  # a signalling NaN: the row path's Python floats quiet it
            a[int(np.flatnonzero(~obs)[0]) if (~obs).any() else 0] = np.frombuffer(b"\x01\x00\x80\x7f", np.float32)[0]
    return a, obs


def _hostile(rng, sid, seq, t):
    """An element the row path refuses (or reads as something other than a plain frame)."""
    k = int(rng.integers(0, 9))
    if k == 0:
        return _frame(sid, seq, t, [1.0] * (C - 1) + [float("inf")])  # infinity: non_finite
    if k == 1:
        return _frame(sid, -3, t, [1.0] * C)  # negative seq: bad_seq
    if k == 2:
        return _frame("", seq, t, [1.0] * C)  # empty stream id
    if k == 3:
        return b"/lacuna/frame\0\0\0,sid\0\0\0\0"  # arguments missing
    if k == 4:
        return b"abcd"  # not an OSC message
    if k == 5:
        return _msg("/lacuna/nothing", [(sid, "s")])  # unknown address
    if k == 6:
        return _frame(sid, seq, t, [1.0] * (C + 1))  # another width: the stream refuses it (row path)
    if k == 7:
        return _bundle([_frame(sid, seq, t, [1.0] * C)])  # a nested bundle (row path)
    return _masked(sid, seq, t, [1.0, float("nan")] + [0.0] * (C - 2), np.ones(C, bool))  # observed NaN


class Net:
    """The client's sockets: the studio's, an intruder's, and one that marks the end of a turn's answers."""

    def __init__(self):
        self.studio, self.intruder, self.marker = (socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(3))
        for s in (self.studio, self.intruder, self.marker):
            s.bind(("127.0.0.1", 0))
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        self.studio.settimeout(10.0)

    def close(self):
        for s in (self.studio, self.intruder, self.marker):
            s.close()

    def turn(self, d, clock, sends):
        """Send ``sends`` ((socket, datagram, arrived)) to daemon ``d``, take them from its socket
        as its turn's items, run the turn, return the datagrams it answered (to either socket)."""
        port = d.net.udp.getsockname()
        for sock, data, _ in sends:
            sock.sendto(data, port)
        items = []
        for _, _, arrived in sends:
            assert select.select([d.net.udp], [], [], 10.0)[0], "a datagram did not arrive"
            data, addr = d.net.udp.recvfrom(1 << 16)
            items.append((data, ("osc", addr), arrived))
        assert [i[0] for i in items] == [s[1] for s in sends]  # (loopback kept the order)
        d.turn(clock(), items=items)
        got = []
        for sock in (self.studio, self.intruder):
            self.marker.sendto(MARK, sock.getsockname())
            sock.settimeout(10.0)
            while (m := sock.recv(1 << 16)) != MARK:
                got.append((sock is self.studio, m))
        return got


def _daemon(clock, arrays, overdue, model):
    cfg = config.from_dict({"daemon": {"budget_ms": 4.0, "max_streams": 64, "log_level": "error", "overdue": overdue,
                                       "max_batch": 64},
                            "models": {"pt": {"builtin": "passthrough"}}, "zmq": {"router": "tcp://127.0.0.1:*"},
                            "osc": {"listen": "127.0.0.1:0"}})
    d = server.Daemon(cfg, server.Log("error"), clock=clock)
    d.start()
    table, errors = load_all(cfg)
    assert not errors
    if model is not None:
        table["st"] = Loaded("st", model, table["pt"].spec, None, "now")
        d._install(table)
    # (no answer may depend on the wall clock: the per-peer budgets are real-time token buckets)
    d.budget = budget.Budget(1e9, 1e9)
    d.osc_err_budget = budget.Budget(1e9, 1e9)
    d.sessions.block_path = arrays
    return d


def _turns(rng, sids, model, n_turns, clock, net):
    seqs = dict.fromkeys(sids, 0)
    for k in range(n_turns):
        sends = []
        now = clock.t + 1 / 120
        t = now - 0.001 - (0.2 if rng.random() < 0.1 else 0.0)
        arrived = now - (float(rng.uniform(0.0030, 0.0040)) if rng.random() < 0.3 else 0.0)
        if k == 0 or rng.random() < 0.04:  # a (re-)handshake of one stream or all
            for sid in (sids if k == 0 else [str(rng.choice(sids))]):
                sends.append((net.studio, _hello(sid, model), arrived))
        if rng.random() < 0.08:  # a single frame ahead of the bundle
            sid = str(rng.choice(sids))
            sends.append((net.studio, _frame(sid, seqs[sid] + 1, t, _values(rng, False)[0]), arrived))
        masked = bool(rng.random() < 0.3)
        for _b in range(2 if rng.random() < 0.1 else 1):
            order = list(sids)
            if rng.random() < 0.2:
                rng.shuffle(order)
            if rng.random() < 0.1:
                order = order[: int(rng.integers(1, len(order) + 1))]
            els = []
            for sid in order:
                seqs[sid] += int(rng.choice([1] * 80 + [2, 4, 0, -1]))
                a, obs = _values(rng, masked)
                q = max(seqs[sid], 0)
                els.append(_masked(sid, q, t, a, obs) if masked else
                           _frame(sid, q, t, a, seqtag=str(rng.choice(["i", "h"])), ttag=str(rng.choice(["d", "f"]))))
            if rng.random() < 0.15:  # a hostile element among them
                els.insert(int(rng.integers(0, len(els) + 1)), _hostile(rng, str(rng.choice(sids)), seqs[sids[0]], t))
            data = _bundle(els)
            if rng.random() < 0.05:  # truncated on its way: the rest of the bundle cannot be read
                data = data[: int(rng.integers(17, len(data)))]
            sender = net.intruder if rng.random() < 0.04 else net.studio  # someone else's bundle of the streams
            sends.append((sender, data, arrived))
        if rng.random() < 0.08:  # a single frame after it
            sid = str(rng.choice(sids))
            seqs[sid] += 1
            sends.append((net.studio, _frame(sid, seqs[sid], t, _values(rng, False)[0]), arrived))
        yield 1 / 120, sends


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("case", ["pt-drop", "pt-serve", "styled-drop"])
def test_osc_bundles_as_arrays_equal_the_row_path_datagrams(case, seed):
    rng = np.random.default_rng(200 + seed)
    clock = FakeClock()
    model_name, overdue = case.split("-")
    model = StyledHold([f"c{i}" for i in range(C)], np.zeros(C), np.ones(C)) if model_name == "styled" else None
    name = "st" if model is not None else "pt"
    net = Net()
    fast, ref = (_daemon(clock, arrays, overdue, model) for arrays in (True, False))
    try:
        n = int(rng.integers(1, 10))
        sids = [f"p{i}" for i in range(n)]
        fills = 0
        for step, sends in _turns(rng, sids, name, 60, clock, net):
            clock.t += step
            got = []
            for d in (fast, ref):
                d.sched.encode_cost, d.sched.send_cost = 20e-6, 40e-6
                got.append(net.turn(d, clock, sends))
            assert got[0] == got[1]
            assert _state(fast) == _state(ref)
            fills += sum(m.startswith(b"#bundle") for _, m in got[0])
        assert fills > 0
        assert fast.sessions.block_served > 0 and ref.sessions.block_served == 0
        assert fast.metrics.counters["osc_bundles_in"] == ref.metrics.counters["osc_bundles_in"] > 0
        if overdue == "drop":
            assert fast.sessions.block_overdue > 0
    finally:
        for d in (fast, ref):
            d.close()
        net.close()


def test_an_intruders_osc_bundle_is_refused_and_a_bad_element_costs_only_itself():
    """The streams' checked plan is kept between bundles: the same streams from another socket are
    refused ``not_owner`` one by one (the owner's streams untouched); a bundle with a refused element
    among the owner's frames still takes the array path, the element answered in the bundle's one
    error answer, counted, the frames served."""
    clock = FakeClock()
    net = Net()
    fast, ref = (_daemon(clock, arrays, "drop", None) for arrays in (True, False))
    try:
        sids = ["a", "b"]
        row = [0.5] * C

        def b(seq, extra=None):
            els = [_frame(s, seq, clock.t, row) for s in sids]
            if extra is not None:
                els.insert(1, extra)
            return _bundle(els)

        turns = [[(net.studio, _hello(s, "pt")) for s in sids] + [(net.studio, b(1))], [(net.studio, b(2))],
                 [(net.intruder, b(3))], [(net.studio, b(3, _frame("a", 9, clock.t, row[:-1] + [float("inf")])))],
                 [(net.studio, b(4, b"junk"))], [(net.studio, b(5)[:-7])]]
        served = []
        for turn in turns:
            clock.t += 1 / 120
            got = [net.turn(d, clock, [(s, m, clock.t) for s, m in turn]) for d in (fast, ref)]
            assert got[0] == got[1]
            assert _state(fast) == _state(ref)
            served.append(fast.sessions.block_served)
        assert served == [1, 2, 2, 3, 4, 5]
        assert ref.metrics.rejected == fast.metrics.rejected == {"not_owner": 2, "non_finite": 1, "not_osc": 1,
                                                                 "malformed": 1}
        errs = [OscMessage(m).params for to_studio, m in got[0] if not m.startswith(b"#bundle")]
        assert errs and errs[0][0] == "malformed"  # (the truncated bundle: b served, a's element cut)
    finally:
        for d in (fast, ref):
            d.close()
        net.close()


def _items(got):
    block, pos, errs = got
    return sorted([*zip(pos, block.frames()), *errs], key=lambda pm: pm[0])


def _same(a, b):
    if isinstance(a, wire.WireError):
        return isinstance(b, wire.WireError) and (a.reason, a.detail, a.stream, a.seq) == (b.reason, b.detail, b.stream, b.seq)
    return isinstance(b, wire.Frame) and (a.stream, a.seq, a.t) == (b.stream, b.seq, b.t) and \
        np.asarray(a.angles).tobytes() == np.asarray(b.angles).tobytes() and \
        (a.observed is None) == (b.observed is None) and \
        (a.observed is None or np.asarray(a.observed).tobytes() == np.asarray(b.observed).tobytes())


def test_read_gives_what_decode_bundle_gives_element_for_element():
    rng = np.random.default_rng(7)
    read = 0
    for k in range(1500):
        masked = bool(rng.random() < 0.3)
        els = []
        for i in range(int(rng.integers(1, 9))):
            a, obs = _values(rng, masked)
            sid = f"s{i}" if rng.random() > 0.02 else "é" * 130
            els.append(_masked(sid, k, k / 120, a, obs) if masked else _frame(sid, k, k / 120, a))
        for _ in range(int(rng.integers(0, 3))):
            els.insert(int(rng.integers(0, len(els) + 1)), _hostile(rng, "s0", k, k / 120))
        data = _bundle(els)
        if rng.random() < 0.1:
            data = data[: int(rng.integers(0, len(data)))]
        if rng.random() < 0.05:  # a byte flipped anywhere
            j = int(rng.integers(0, len(data)))
            data = data[:j] + bytes([data[j] ^ (1 << int(rng.integers(0, 8)))]) + data[j + 1:]
        got = oscblock.read(data, wire.MAX_MESSAGE_BYTES)
        if got is None:
            continue
        read += 1
        want = osc.decode_bundle(data)
        mine = [m for _, m in _items(got)]
        assert len(mine) == len(want) and all(_same(a, b) for a, b in zip(want, mine)), k
    assert read > 800


@pytest.mark.parametrize("seed", range(3))
def test_fill_datagram_is_osc_encode(seed):
    rng = np.random.default_rng(seed)
    for k in range(500):
        n = int(rng.integers(1, 70))
        a = rng.normal(scale=90, size=n).astype(np.float32)
        a[rng.random(n) < 0.1] = np.nan
        style = None if rng.random() < 0.3 else rng.random(int(rng.integers(1, 5)))
        phase = None if rng.random() < 0.3 else float(rng.choice([rng.random(), np.nan, 1e300]))
        msg = wire.FillMsg(f"actor{k}" + "ü" * int(rng.integers(0, 3)), int(rng.integers(0, 1 << 62)), float(rng.random() * 1e4),
                           a, rng.random(n) < 0.5, np.abs(rng.normal(size=n)).astype(np.float32),
                           str(rng.choice(["ok", "degraded", "passthrough"])), "m" * int(rng.integers(1, 9)),
                           int(rng.integers(0, 1 << 30)), None if style is None else np.asarray(style, np.float32),
                           None if phase is None or not np.isfinite(phase) or phase > 1e38 else phase, int(rng.integers(0, 3)))
        assert oscblock.fill_datagram(fill_map(msg)) == osc.encode(msg), k


def test_real_cmu_osc_bundles_over_a_real_daemon_take_the_array_path(data, tmp_path):
    """A capture tool's OSC bundles of real CMU 35_08 frames (left arm lost) to a real daemon
    process: every bundle, the first too, is served as arrays (``bundles_as_arrays``), and each
    fill comes back as its own OSC bundle with the frame's observed values exactly as sent."""
    from pythonosc.osc_bundle import OscBundle

    from clients.control import control
    from clients.harness import DaemonProcess
    from mocap.datasets import load_trial

    take = load_trial("35_08")
    ch = list(take.channels)
    rows = take.frames[:30].astype(np.float32)
    rows[:, [c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "lhand") for c in ch]] = np.nan
    n = 4
    with DaemonProcess({"floor": {"builtin": "passthrough", "channels": ch}}, workdir=tmp_path,
                       daemon={"budget_ms": 250.0, "log_level": "warning"}, osc={"listen": "127.0.0.1:0"}) as d:
        host, port = d.endpoints["osc"].rsplit(":", 1)
        u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        u.bind(("127.0.0.1", 0))
        u.settimeout(10.0)
        try:
            for i in range(n):
                u.sendto(_msg("/lacuna/hello", [(f"actor{i}", "s"), ("", "s")] + [(c, "s") for c in ch]), (host, int(port)))
                assert OscMessage(u.recv(1 << 16)).address == "/lacuna/hello-ack"
            for k in range(len(rows) - n):
                bb = OscBundleBuilder(IMMEDIATELY)
                for i in range(n):
                    bb.add_content(OscMessage(_frame(f"actor{i}", k, k / 120, rows[k + i])))
                u.sendto(bb.build().dgram, (host, int(port)))
                for i in range(n):
                    msgs = {m.address: m.params for m in OscBundle(u.recv(1 << 16))}
                    fill = msgs["/lacuna/fill"]
                    assert fill[:3] == [f"actor{i}", k, k / 120] and fill[3] == "passthrough"
                    got = np.array(fill[7:], np.float32)
                    sent = rows[k + i]
                    assert got.tobytes() == np.where(np.isfinite(sent), sent, np.float32(np.nan)).tobytes()
                    assert msgs["/lacuna/filled"][2] == bytes(len(ch))
            st = control(d.endpoint, "status", timeout_s=10.0).result
            assert st["counters"]["bundles_as_arrays"] == len(rows) - n
            assert st["counters"]["osc_bundles_in"] == len(rows) - n
            assert st["counters"]["frames_out"] == n * (len(rows) - n)
        finally:
            u.close()
