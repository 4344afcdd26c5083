"""Superseded frames of a burst are kept as their heads and answered without a second decode
(daemon/aside.py): the answers, byte for byte, and every counter equal handling each message
in arrival order, through the public ``Daemon.turn``."""
from __future__ import annotations

import msgpack
import numpy as np
import pytest

from daemon import config, dispatch, wire
from daemon.loop import Daemon
from daemon.models import load_all

C = 5


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def _daemon(clock: Clock, in_order: bool) -> tuple[Daemon, list[bytes]]:
    """A pass-through daemon whose answers are kept as the bytes the transport would send, in
    order, with whom they go to; ``in_order``: a turn's messages are handled one by one, nothing
    set aside (the reference)."""
    cfg = config.from_dict({"daemon": {"budget_ms": 100.0, "max_streams": 8, "log_level": "error", "overdue": "serve"},
                            "models": {"pt": {"builtin": "passthrough"}}, "zmq": {"router": "tcp://127.0.0.1:*"}})

    class D(Daemon):
        def _batch(self, items):  # type: ignore[no-untyped-def]
            if not in_order:
                return super()._batch(items)
            old, dispatch.BATCH_MIN = dispatch.BATCH_MIN, 10**9
            try:
                return super()._batch(items)
            finally:
                dispatch.BATCH_MIN = old

    d = D(cfg, clock=clock)
    table, errors = load_all(cfg)
    assert not errors
    d._install(table)
    sent: list[bytes] = []
    d._send = lambda o, m, publish=False: sent.append(repr(o).encode() + b" " + wire.encode(m))  # type: ignore[method-assign]
    for sid in ("a", "b"):
        d.turn(clock(), items=[(wire.encode(wire.Hello(sid, [f"ch{i}" for i in range(C)])), _peer(sid), clock())])
    sent.clear()
    return d, sent


def _peer(sid: str) -> tuple:
    return ("router", [f"peer-{sid}".encode()])


def _frame(sid: str, seq: int, v: np.ndarray, t: float = 0.0) -> bytes:
    return wire.encode(wire.Frame(sid, seq, t, v))


def _mixed_burst(rng: np.random.Generator, turn: int, clock: Clock) -> list[tuple[bytes, tuple, float]]:
    """Single frames of streams a and b interleaved, runs of one stream, duplicates, late ones,
    and malformed ones among them (infinity, a wrong width, not msgpack, a bool version).  One
    capture time for all: a session's delivery baseline (``frames_waited``) depends on the order
    its frames' (arrival - capture) come in, and the served frame is taken before those it
    superseded (as before daemon/aside.py), so with mixed capture times that counter may differ."""
    items = []
    seqs = {"a": 100 * turn, "b": 100 * turn}
    for _ in range(int(rng.integers(3, 40))):
        sid = "a" if rng.random() < 0.6 else "b"
        seqs[sid] += int(rng.choice([1, 1, 1, 2, 0, -1]))
        v = rng.normal(size=C).astype(np.float32)
        v[rng.random(C) < 0.3] = np.nan
        r = rng.random()
        seq = max(seqs[sid], 0)
        if r < 0.04:
            data = b"\x93not a map"
        elif r < 0.08:
            data = _frame(sid, seq, np.ones(C + 1, np.float32))
        elif r < 0.12:
            v[0] = np.inf
            data = _frame(sid, seq, v)
        elif r < 0.15:
            m = wire.to_map(wire.Frame(sid, seq, 0.0, v))
            m["v"] = True  # (== 1, yet not a version)
            data = msgpack.packb(m, use_bin_type=True)
        elif r < 0.18:
            m = wire.to_map(wire.Frame(sid, seq, 0.0, v))
            m["t"] = 0  # an int time: valid, off the decoder's fast path
            data = msgpack.packb(m, use_bin_type=True)
        elif r < 0.22:
            data = wire.encode(wire.Frame(sid, seq, 0.0, v, np.isfinite(v)))
        else:
            data = _frame(sid, seq, v)
        items.append((data, _peer(sid), clock()))
    return items


@pytest.mark.parametrize("seed", range(8))
def test_set_aside_answers_are_byte_identical_to_in_order_handling(seed):
    rng = np.random.default_rng(seed)
    clock = Clock()
    (fast, got), (ref, want) = _daemon(clock, False), _daemon(clock, True)
    set_aside = 0
    for turn in range(12):
        clock.t += 1 / 120
        items = _mixed_burst(rng, turn, clock)
        set_aside += fast.turn(clock(), items=list(items))
        assert ref.turn(clock(), items=list(items)) == 0
        assert sorted(got) == sorted(want), f"turn {turn}"  # (the order differs: set-aside answers come after the fills)
        got.clear()
        want.clear()
        assert fast.metrics.counters == ref.metrics.counters and fast.metrics.rejected == ref.metrics.rejected
        for sid in ("a", "b"):
            f, r = fast.sessions.sessions[sid], ref.sessions.sessions[sid]
            assert (f.counts, f.last_seq, f.t_base) == (r.counts, r.last_seq, r.t_base)
    assert set_aside > 20  # the set-aside path was exercised


def test_a_run_of_one_streams_frames_is_decoded_once_each(monkeypatch):
    """Ten frames of one stream and a duplicate in one turn: the served one is decoded, the nine
    it superseded and the duplicate are answered from their heads, not decoded again; a malformed
    one among them is decoded (its error needs it)."""
    clock = Clock()
    d, sent = _daemon(clock, False)
    calls = []  # (the real decoder, each call's seq noted)
    real = wire.decode_map
    monkeypatch.setattr(wire, "decode_map", lambda m: calls.append(m.get("seq")) or real(m))
    v = np.arange(C, dtype=np.float32)
    bad = v.copy()
    bad[1] = np.inf
    items = [(_frame("a", s, v), _peer("a"), clock()) for s in range(1, 11)]
    items.insert(4, (_frame("a", 4, v), _peer("a"), clock()))  # a duplicate of 4
    items.insert(3, (_frame("a", 3, bad), _peer("a"), clock()))  # malformed
    assert d.turn(clock(), items=items) == 11  # (all but the served one set aside)
    assert sorted(calls) == [3, 10]
    answers = [wire.decode(b.split(b" ", 2)[-1]) for b in sent]
    assert isinstance(answers[0], wire.FillMsg) and answers[0].seq == 10
    assert sorted((m.seq, getattr(m, "reason", None)) for m in answers[1:]) == \
        sorted([(s, "conflated") for s in range(1, 10)] + [(3, "non_finite"), (4, "duplicate")])


def test_head_is_only_given_for_what_the_decoder_takes_and_agrees_with_it():
    from daemon import aside  # (here: the tests above also run against a tree from before it)

    v = np.array([0.5, np.nan, 2.0], np.float32)
    good = wire.to_map(wire.Frame("a", 7, 1.5, v))
    masked = wire.to_map(wire.Frame("a", 7, 1.5, v, np.array([1, 0, 1], bool)))
    variants = {"good": good, "masked": masked}
    for name, change in {"v bool": ("v", True), "v float": ("v", 1.0), "t int": ("t", 1), "t inf": ("t", float("inf")),
                         "seq negative": ("seq", -1), "seq bool": ("seq", True), "empty angles": ("angles", b""),
                         "odd bytes": ("angles", b"\x00" * 5), "stream empty": ("stream", ""),
                         "stream unprintable": ("stream", "a\n"), "infinity": ("angles", np.float32([np.inf, 0]).tobytes()),
                         "mask 2": ("observed", b"\x02\x00\x01"), "mask short": ("observed", b"\x01")}.items():
        variants[name] = {**good, change[0]: change[1]}
    variants["observed nan"] = {**masked, "observed": b"\x01\x01\x01"}
    for name, m in variants.items():
        h = aside.head(m)
        try:
            f = wire.decode_map(m)
        except wire.WireError:
            assert h is None, name
            continue
        assert h is None or h == (f.seq, f.t, f.angles.shape[0]), name
    assert aside.head(good) == (7, 1.5, 3) and aside.head(masked) == (7, 1.5, 3)
    assert aside.head(variants["t int"]) is None  # (valid, but off the fast path: kept as its map, decoded)


def test_a_failed_turn_answers_every_set_aside_frame_with_an_error(monkeypatch):
    """When the turn's step fails, each frame waiting or set aside (a run of heads or a map kept
    to be decoded) is answered with an ``internal`` error carrying its seq."""
    clock = Clock()
    d, sent = _daemon(clock, False)
    v = np.arange(C, dtype=np.float32)
    m = wire.to_map(wire.Frame("a", 4, 0.0, v))
    m["t"] = 0  # valid, off the fast path: kept as its map
    items = [(_frame("a", s, v), _peer("a"), clock()) for s in (1, 2, 3, 5, 6)]
    items.insert(3, (msgpack.packb(m, use_bin_type=True), _peer("a"), clock()))

    def fail() -> None:
        raise RuntimeError("a step that fails")

    monkeypatch.setattr(d, "_serve", fail)
    assert d.turn(clock(), items=items) == 5
    answers = [wire.decode(b.split(b" ", 2)[-1]) for b in sent]
    assert sorted((type(m).__name__, m.seq, m.reason) for m in answers) == \
        [("ErrorMsg", s, "internal") for s in (1, 2, 3, 4, 5, 6)]
