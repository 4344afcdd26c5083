"""A bundle served as arrays (daemon/blockpath.py, daemon/tickblock.py) against the row path:
two daemons, one with the array path and one without, get the same fuzzed turns (bundles in
and out of order, gaps, duplicates and late frames, single frames superseding bundled ones in
the same turn, two bundles a turn, malformed elements, re-handshakes, frames that waited, masks,
frames overdue after the step, streams held by the scheduler) and must send the same bytes in
the same order and end in the same state: every session's sequence numbers, streaks, counters,
last frame and filter state, the global counters, the latency window and the scheduler's cost
estimates.  One fake clock, so no answer depends on how fast the machine is."""
from __future__ import annotations

import msgpack
import numpy as np
import pytest

from daemon import config, server, wire
from daemon.models import Loaded, load_all
from daemon.pack import fill_map, to_map
from lacuna.filler import Fill
from mocap.baselines import HoldModel

C = 6
PEER = ("router", [b"studio"])
PULL = ("pull", None)  # (a PULL or SUB input: answers go to PUB)


class FakeClock:
    def __init__(self, t: float = 1000.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


class StyledHold(HoldModel):
    """A hold model whose fills carry a style posterior and a phase (as the HLM's do), with
    three quality levels (as the CRBM's): what the array path must carry through unchanged."""

    method = "styled-hold"

    def quality_levels(self):
        return [4, 2, 1]

    def step_batch(self, states, frames, observed, level=None):
        fills = super().step_batch(states, frames, observed)
        out = []
        for f in fills:
            v = float(np.nansum(f.frame))
            phase = None if v > 3 else (float("nan") if v < -3 else (v % 1.0))
            out.append(Fill(f.frame, f.std, f.filled, {"style": np.array([abs(v) % 1, 1 - abs(v) % 1]), "phase": phase}))
        return out


class Recording(server.Daemon):
    def _send(self, origin, msg, publish=False):
        m = fill_map(msg) if type(msg) is wire.FillMsg else to_map(msg)
        self.sent.append((repr(origin), msgpack.packb(m, use_bin_type=True)))

    def _send_fills(self, origin, maps):
        for m in maps:
            self.sent.append((repr(origin), msgpack.packb(m, use_bin_type=True)))


def _daemon(clock, arrays: bool, overdue: str, model):
    cfg = config.from_dict({"daemon": {"budget_ms": 4.0, "max_streams": 64, "log_level": "error", "overdue": overdue,
                                       "max_batch": 64},
                            "models": {"pt": {"builtin": "passthrough"}}, "zmq": {"router": "tcp://127.0.0.1:*"}})
    d = Recording(cfg, server.Log("error"), clock=clock)
    d.sent = []
    table, errors = load_all(cfg)
    assert not errors
    if model is not None:
        table["st"] = Loaded("st", model, table["pt"].spec, None, "now")
    d._install(table)
    if not arrays:
        d.sessions.block_path = False
    return d


def _frame_map(rng, sid, seq, t, masked):
    a = rng.normal(scale=2, size=C).astype(np.float32)
    obs = rng.random(C) > 0.3
    d = {"stream": sid, "seq": seq, "t": t}
    if masked:
        a[~obs] = rng.choice([np.nan, 5.0])
        d.update(angles=a.tobytes(), observed=obs.astype(np.uint8).tobytes())
    else:
        a[~obs] = np.nan
        d.update(angles=a.tobytes())
    return d


def _turns(rng, sids, model_name, n_turns, clock, peer=PEER):
    """(advance the clock by, items) per turn: the studio's bundles and the odd other message."""
    seqs = dict.fromkeys(sids, 0)
    for k in range(n_turns):
        items = []
        now = clock.t + 1 / 120
        masked = bool(rng.random() < 0.3)
        # the capture stamp: usually on time, now and then a frame that waited on its way
        t = now - 0.001 - (0.2 if rng.random() < 0.1 else 0.0)
        # received up to the budget ago: some are answered overdue before the step, some after it
        arrived = now - (float(rng.uniform(0.0030, 0.0040)) if rng.random() < 0.3 else 0.0)
        r = rng.random()
        if k == 0 or r < 0.05:  # a (re-)handshake of one stream or all
            for sid in (sids if k == 0 else [str(rng.choice(sids))]):
                items.append((wire.encode(wire.Hello(sid, [f"c{i}" for i in range(C)], model_name)), peer, arrived))
        if rng.random() < 0.1:  # a single frame ahead of the bundle (the bundle's frame supersedes it)
            sid = str(rng.choice(sids))
            items.append((msgpack.packb({"v": 1, "type": "frame", **_frame_map(rng, sid, seqs[sid] + 1, t, False)},
                                        use_bin_type=True), peer, arrived))
        for _b in range(2 if rng.random() < 0.1 else 1):
            order = list(sids)
            if rng.random() < 0.2:
                rng.shuffle(order)
            if rng.random() < 0.1:
                order = order[: int(rng.integers(1, len(order) + 1))]
            els = []
            for sid in order:
                seqs[sid] += int(rng.choice([1] * 80 + [2, 4, 0, -1]))
                els.append(_frame_map(rng, sid, max(seqs[sid], 0), t, masked))
            if rng.random() < 0.05:
                els[0]["angles"] = b"\0" * (4 * C + 4)  # a malformed element: not a regular bundle
            items.append((msgpack.packb({"v": 1, "type": "frames", "frames": els}, use_bin_type=True), peer, arrived))
        if rng.random() < 0.1:  # a single frame after it: it supersedes the bundle's (or is late)
            sid = str(rng.choice(sids))
            seqs[sid] += 1
            items.append((msgpack.packb({"v": 1, "type": "frame", **_frame_map(rng, sid, seqs[sid], t, False)},
                                        use_bin_type=True), peer, arrived))
        yield 1 / 120, items


def _state(d):
    out = {}
    for sid, s in sorted(d.sessions.sessions.items()):
        st = s.state
        out[sid] = (s.last_seq, s.model_seq, s.held_streak, s.late_streak, dict(s.counts), s.t_base, s.max_wait_s,
                    s.pending, s.owner, None if s.last_out is None else s.last_out.tobytes(),
                    getattr(st, "last", np.zeros(0)).tobytes())
    sched = d.sched
    costs = {(k[1]): list(v.s) for k, v in sched.costs.items()}
    counters = {k: v for k, v in d.metrics.counters.items() if k != "bundles_as_arrays"}  # (the one allowed difference)
    return (out, counters, d.metrics._n, d.metrics._lat[: d.metrics._n].tobytes(), costs,
            sched.reply_cost, sched.encode_cost, sched.send_cost, sched.probes, list(sched.hold_cost.s))


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("case", ["pt-drop", "pt-serve", "styled-drop", "styled-held", "pt-drop-pull", "styled-drop-pull"])
def test_block_path_answers_and_state_equal_row_path(case, seed):
    rng = np.random.default_rng(seed)
    clock = FakeClock()
    model_name, overdue, *via = case.split("-")
    peer = PULL if via else PEER
    model = StyledHold([f"c{i}" for i in range(C)], np.zeros(C), np.ones(C)) if model_name == "styled" else None
    name = "st" if model is not None else "pt"
    fast, ref = (_daemon(clock, arrays, "serve" if overdue == "serve" else "drop", model) for arrays in (True, False))
    n = int(rng.integers(1, 12))
    sids = [f"p{i}" for i in range(n)]
    for step, items in _turns(rng, sids, name, 60, clock, peer):
        clock.t += step
        for d in (fast, ref):
            # fixed reply costs (a fake clock would let them decay to nothing): frames received
            # received 3-4 ms ago are then answered overdue from some place in the tick on
            d.sched.encode_cost, d.sched.send_cost = 20e-6, 40e-6
            if overdue == "held":  # the model costs more than the budget: the scheduler holds
                for lv in (4, 2, 1):
                    d.sched.cost(model, lv).s = [1.0, 1.0, 1.0, 0.01, 0.01]
            d.turn(clock(), items=list(items))
        assert fast.sent == ref.sent
        assert _state(fast) == _state(ref)
        fast.sent.clear()
        ref.sent.clear()
    # the array path did serve (not only decline), the overload case too (frames overdue at the tick's start)
    assert fast.sessions.block_served > 0 and ref.sessions.block_served == 0
    if overdue == "drop":
        assert fast.sessions.block_overdue > 0


@pytest.mark.parametrize("case", ["pt", "styled"])
def test_first_bundle_after_the_hellos_is_served_as_arrays_as_the_row_path_serves_it(case):
    """A stream's first frames (its hello just answered, no frame numbered yet): the bundle that
    opens the numbering takes the array path too, in the hellos' turn and in the next one, with
    the same answers and states as the row path; a re-handshake of one stream starts it over."""
    clock = FakeClock()
    model = StyledHold([f"c{i}" for i in range(C)], np.zeros(C), np.ones(C)) if case == "styled" else None
    name = "st" if model is not None else "pt"
    fast, ref = (_daemon(clock, arrays, "drop", model) for arrays in (True, False))
    rng = np.random.default_rng(3)
    sids = ["a", "b", "c"]
    hello = [wire.encode(wire.Hello(sid, [f"c{i}" for i in range(C)], name)) for sid in sids]

    def bundle(seqs):
        els = [_frame_map(rng, sid, q, clock.t - 0.001, False) for sid, q in zip(sids, seqs)]
        return msgpack.packb({"v": 1, "type": "frames", "frames": els}, use_bin_type=True)

    for turn in ([*hello, [7, 0, 3]], [[8, 1, 4]], [hello[1]], [[9, 5, 5]]):
        clock.t += 1 / 120
        items = [(m if isinstance(m, bytes) else bundle(m), PEER, clock.t) for m in turn]
        for d in (fast, ref):
            d.turn(clock(), items=list(items))
        assert fast.sent == ref.sent
        assert _state(fast) == _state(ref)
    assert any(b"fill" in m for _, m in fast.sent)
    assert fast.sessions.block_served == 3 and ref.sessions.block_served == 0


@pytest.mark.parametrize("case", ["pt", "styled"])
@pytest.mark.parametrize("overdue", ["drop", "serve"])
def test_a_bundle_superseding_the_waiting_one_stays_on_the_array_path(case, overdue):
    """A daemon behind reads two or three bundles of the same streams in one turn: each newer one
    supersedes the one waiting as a block (its frames answered ``conflated`` after the fills, as
    the row path answers them), and the newest is served as arrays; one with a frame not newer
    than the one waiting (a duplicate), or of other streams, goes to the row path, with the
    same answers."""
    clock = FakeClock()
    model = StyledHold([f"c{i}" for i in range(C)], np.zeros(C), np.ones(C)) if case == "styled" else None
    name = "st" if model is not None else "pt"
    fast, ref = (_daemon(clock, arrays, overdue, model) for arrays in (True, False))
    rng = np.random.default_rng(11)
    sids = ["a", "b", "c", "d"]
    hello = [wire.encode(wire.Hello(sid, [f"c{i}" for i in range(C)], name)) for sid in sids]

    def bundle(seqs, who=sids):
        masked = bool(rng.random() < 0.5)  # (a regular bundle: every element masked, or none)
        els = [_frame_map(rng, sid, q, clock.t - 0.001, masked) for sid, q in zip(who, seqs)]
        return msgpack.packb({"v": 1, "type": "frames", "frames": els}, use_bin_type=True)

    served = []
    for turn in ([*hello, [1, 1, 1, 1]], [[2, 2, 2, 2], [3, 4, 3, 3]], [[5, 5, 5, 5], [6, 6, 6, 6], [9, 7, 8, 7]],
                 [[10, 10, 10, 10], [11, 10, 11, 11]], [[12, 12, 12, 12], ("ab", [13, 13])]):
        clock.t += 1 / 120
        items = [(m if isinstance(m, bytes) else bundle(m) if isinstance(m, list) else bundle(m[1], list(m[0])),
                  PEER, clock.t) for m in turn]
        for d in (fast, ref):
            d.turn(clock(), items=list(items))
        assert fast.sent == ref.sent
        assert _state(fast) == _state(ref)
        served.append(fast.sessions.block_served)
    assert ref.metrics.counters["dropped_conflated"] == 4 + 8 + 3 + 2  # (turn 4: b is a duplicate)
    # the first three turns' newest bundles on the array path; the duplicate's and the other streams' not
    assert served == [1, 2, 3, 3, 3]


@pytest.mark.parametrize("start,n", [(0, 5), (19990, 30), (5, 20000), (19999, 1)])
def test_latencies_equal_latency_n_times(start, n):
    from daemon.metrics import Metrics

    a, b = Metrics(), Metrics()
    for m in (a, b):
        m._n = start
        m._lat[:] = -1.0
    a.latencies(0.25, n)
    for _ in range(n):
        b.latency(0.25)
    assert a._n == b._n and a._lat.tobytes() == b._lat.tobytes()


def test_real_cmu_bundles_over_a_real_daemon_take_the_array_path(data, tmp_path):
    """A studio's bundles of real CMU 35_08 frames (left arm lost) to a real daemon over ZeroMQ:
    every one of them, the first (which opens the streams' numbering) too, is served as arrays
    (status counter ``bundles_as_arrays``), and every fill gives the frame's observed values
    exactly as sent, NaN and ``filled`` nowhere (pass-through), in one ``replies`` a bundle,
    the same fields in every reply."""
    import zmq

    from clients.control import control
    from clients.harness import DaemonProcess
    from mocap.datasets import load_trial

    take = load_trial("35_08")
    ch = list(take.channels)
    rows = take.frames[:40].astype(np.float32)
    rows[:, [c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "lhand") for c in ch]] = np.nan
    n = 8
    with DaemonProcess({"floor": {"builtin": "passthrough", "channels": ch}}, workdir=tmp_path,
                       daemon={"budget_ms": 250.0, "log_level": "warning"}) as d:
        ctx = zmq.Context()
        s = ctx.socket(zmq.DEALER)
        s.setsockopt(zmq.LINGER, 0)
        s.connect(d.endpoint)
        try:
            for i in range(n):
                s.send(wire.encode(wire.Hello(f"actor{i}", ch)))
                assert s.poll(10000) and isinstance(wire.decode(s.recv()), wire.HelloAck)
            fields = []
            for k in range(len(rows) - n):
                b = wire.Bundle([wire.Frame(f"actor{i}", k, k / 120, rows[k + i]) for i in range(n)])
                s.send(wire.encode(b))
                assert s.poll(10000)
                rep = wire.decode(s.recv(), 64 << 20)
                assert isinstance(rep, wire.Replies) and len(rep.items) == n
                for i, f in enumerate(rep.items):
                    assert isinstance(f, wire.FillMsg) and (f.stream, f.seq, f.status) == (f"actor{i}", k, "passthrough")
                    sent = rows[k + i]
                    assert f.angles.tobytes() == np.where(np.isfinite(sent), sent, np.float32(np.nan)).tobytes()
                    assert not f.filled.any() and not f.std.any()
                fields.append(sorted(wire.to_map(rep.items[0])))
            assert all(f == fields[0] for f in fields)
            st = control(d.endpoint, "status", timeout_s=10.0).result
            assert st["counters"]["bundles_as_arrays"] == len(rows) - n
            assert st["counters"]["frames_out"] == n * (len(rows) - n)
        finally:
            s.close(0)
            ctx.term()


def test_real_cmu_bundles_pushed_over_pull_are_served_as_arrays_and_published(data, tmp_path):
    """The same bundles PUSHed to the daemon's PULL input (hellos too, so the PULL side owns the
    streams): served as arrays, first bundle included, each fill published on PUB under its
    stream's topic, one message per fill (not a ``replies``), the observed values exactly as sent."""
    import zmq
    from waiting import wait_until

    from clients.control import control
    from clients.harness import DaemonProcess
    from mocap.datasets import load_trial

    take = load_trial("35_08")
    ch = list(take.channels)
    rows = take.frames[:24].astype(np.float32)
    rows[:, [c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "lhand") for c in ch]] = np.nan
    n = 4
    with DaemonProcess({"floor": {"builtin": "passthrough", "channels": ch}}, workdir=tmp_path,
                       daemon={"budget_ms": 250.0, "log_level": "warning"},
                       zmq={"pull": "tcp://127.0.0.1:*", "pub": "tcp://127.0.0.1:*"}) as d:
        ctx = zmq.Context()
        sub, push = ctx.socket(zmq.SUB), ctx.socket(zmq.PUSH)
        try:
            for s in (sub, push):
                s.setsockopt(zmq.LINGER, 0)
            sub.setsockopt(zmq.SUBSCRIBE, b"")
            sub.connect(d.endpoints["pub"])
            push.connect(d.endpoints["pull"])
            # PUB/SUB's slow joiner: joined once a hello's ack comes through on PUB
            wait_until(lambda: push.send(wire.encode(wire.Hello("join", ch))) or sub.poll(50), 10, "a published ack")
            while sub.poll(200):
                sub.recv_multipart()

            def published(k: int) -> list[tuple[bytes, wire.Message]]:
                got = []
                for _ in range(k):
                    assert sub.poll(10000), "nothing published"
                    topic, body = sub.recv_multipart()
                    got.append((topic, wire.decode(body)))
                return got

            for i in range(n):
                push.send(wire.encode(wire.Hello(f"actor{i}", ch)))
            assert all(isinstance(m, wire.HelloAck) for _, m in published(n))
            for k in range(len(rows) - n):
                push.send(wire.encode(wire.Bundle([wire.Frame(f"actor{i}", k, k / 120, rows[k + i]) for i in range(n)])))
                for i, (topic, f) in enumerate(published(n)):
                    assert topic == f"actor{i}".encode() and isinstance(f, wire.FillMsg)
                    assert (f.stream, f.seq, f.status) == (f"actor{i}", k, "passthrough")
                    sent = rows[k + i]
                    assert f.angles.tobytes() == np.where(np.isfinite(sent), sent, np.float32(np.nan)).tobytes()
                    assert not f.filled.any() and not f.std.any()
            st = control(d.endpoint, "status", timeout_s=10.0).result
            assert st["counters"]["bundles_as_arrays"] == len(rows) - n
            assert st["counters"]["frames_out"] == n * (len(rows) - n)
            # (no answer was lost or failed on its way)
            assert st["counters"].get("send_errors", 0) == 0 and st["counters"].get("send_dropped", 0) == 0
        finally:
            sub.close(0)
            push.close(0)
            ctx.term()


def test_a_bundle_from_another_connection_is_refused_as_the_row_path_refuses_it():
    """The checked plan of a set of streams is kept between bundles: a bundle naming the same
    streams from a connection that does not own them must still be refused (``not_owner``, the
    owner's streams untouched), not served through the plan the owner's bundles made."""
    clock = FakeClock()
    other = ("router", [b"intruder"])
    fast, ref = (_daemon(clock, arrays, "drop", None) for arrays in (True, False))
    rng = np.random.default_rng(5)
    sids = ["a", "b"]

    def bundle(seqs):
        els = [_frame_map(rng, sid, q, clock.t - 0.001, False) for sid, q in zip(sids, seqs)]
        return msgpack.packb({"v": 1, "type": "frames", "frames": els}, use_bin_type=True)

    hello = [(wire.encode(wire.Hello(sid, [f"c{i}" for i in range(C)], "pt")), PEER) for sid in sids]
    for turn in (hello + [([1, 1], PEER)], [([2, 2], PEER)], [([3, 3], other)], [([3, 3], PEER)]):
        clock.t += 1 / 120
        items = [(m if isinstance(m, bytes) else bundle(m), who, clock.t) for m, who in turn]
        for d in (fast, ref):
            d.turn(clock(), items=list(items))
        assert fast.sent == ref.sent
        assert _state(fast) == _state(ref)
    assert ref.metrics.rejected.get("not_owner") == 2 and fast.metrics.rejected == ref.metrics.rejected
