"""The vectorised wire path against the row-by-row one: a bundle read as arrays (daemon/block.py)
gives exactly the frames and errors of reading each element alone, and a tick's answers packed
in one pass (encode.replies_of) are the bytes of encoding each and joining them.  Real CMU
frames and fuzzed ones; no sockets."""
from __future__ import annotations

import msgpack
import numpy as np
import pytest

from daemon import wire as w
from daemon.block import read_block
from daemon.decode import _decode_frame


def _pack(d):
    return msgpack.packb(d, use_bin_type=True)


def _element(rng, i, C, masked, values=None):
    a = rng.normal(scale=40, size=C).astype(np.float32) if values is None else values.astype(np.float32).copy()
    obs = rng.random(C) > 0.3 if values is None else np.isfinite(a)
    d = {"stream": f"p{i}", "seq": int(rng.integers(0, 1 << 40)), "t": float(rng.uniform(0, 2e9))}
    if masked:
        a[~obs] = rng.choice([np.nan, np.inf, 7.0])  # a slot the mask calls missing may hold anything
        d.update(angles=a.tobytes(), observed=obs.astype(np.uint8).tobytes())
    else:
        a[~obs] = np.nan
        d.update(angles=a.tobytes())
    return d


# frame-level faults the element-by-element path names (each alone is a frame it refuses or reads)
MUTATIONS = (
    lambda e, C: {**e, "angles": b"\0" * 4 * (C + 1)},             # another width
    lambda e, C: {**e, "angles": np.full(C, np.inf, np.float32).tobytes()},
    lambda e, C: {**e, "observed": b"\2" * C},
    lambda e, C: {**e, "observed": b"\1" * (C + 1)},
    lambda e, C: {**e, "observed": b"\1" * C},                     # NaN marked observed (or a mask where others have none)
    lambda e, C: {**e, "t": float("inf")},
    lambda e, C: {**e, "t": 3},                                    # an int stamp: read by the checked path
    lambda e, C: {**e, "seq": -1},
    lambda e, C: {**e, "seq": True},
    lambda e, C: {**e, "stream": "a\nb"},
    lambda e, C: {**e, "stream": ""},
    lambda e, C: {k: v for k, v in e.items() if k != "angles"},
    lambda e, C: {**e, "extra": [1, 2]},                           # unknown keys are ignored
    lambda e, C: {**e, "angles": "not bytes"},
)


def _alone(e):
    """The row-by-row path: the element read as the frame it is (what a bundle's element gets
    when the bundle is not regular, and what the same frame sent alone gets, bar the v/type keys)."""
    try:
        return _decode_frame(e)
    except w.WireError as err:
        return err


def _same(x, y):
    if isinstance(x, w.WireError) or isinstance(y, w.WireError):
        assert isinstance(x, w.WireError) and isinstance(y, w.WireError), (x, y)
        assert (x.reason, x.detail, x.stream, x.seq) == (y.reason, y.detail, y.stream, y.seq)
        return
    assert (x.stream, x.seq, x.t) == (y.stream, y.seq, y.t)
    assert x.angles.dtype == y.angles.dtype and np.array_equal(x.angles, y.angles, equal_nan=True)
    assert (x.observed is None) == (y.observed is None)
    if x.observed is not None:
        assert x.observed.dtype == y.observed.dtype and np.array_equal(x.observed, y.observed)


def _check_bundle(els, expect_block):
    m = w.decode(_pack({"v": 1, "type": "frames", "frames": els}))
    assert isinstance(m, w.Bundle) and len(m.items) == len(els)
    for x, e in zip(m.items, els):
        _same(x, _alone(e))
    if expect_block is not None:
        assert (m.block is not None) == expect_block
    # the block is taken only when the row path would read every element as a frame
    assert m.block is None or not any(isinstance(x, w.WireError) for x in m.items)
    if m.block is not None:
        b = m.block
        assert len(b) == len(els) and b.values.shape == (len(els), len(els[0]["angles"]) // 4)
        assert b.sids == [f.stream for f in m.items] and b.seqs == [f.seq for f in m.items]
        assert np.array_equal(b.observed(), np.array([np.isfinite(f.angles) if f.observed is None else f.observed
                                                      for f in m.items]))
        # every frame is a row of the block's one buffer, nothing copied per frame
        assert all(np.shares_memory(f.angles, b.values) for f in m.items)
    return m


def test_regular_fuzzed_bundles_are_read_as_one_block_equal_to_each_element_alone(rng):
    for trial in range(200):
        C = int(rng.choice([1, 5, 62, 300]))
        masked = bool(trial % 2)
        els = [_element(rng, i, C, masked) for i in range(int(rng.integers(1, 40)))]
        _check_bundle(els, expect_block=True)


def test_a_bundle_with_one_faulty_element_takes_the_row_path_and_every_answer_stays_the_same(rng):
    for trial in range(400):
        C = int(rng.choice([1, 4, 62]))
        masked = bool(trial % 2)
        els = [_element(rng, i, C, masked) for i in range(int(rng.integers(2, 12)))]
        j = int(rng.integers(len(els)))
        mut = MUTATIONS[trial % len(MUTATIONS)]
        els[j] = mut(els[j], C)
        m = _check_bundle(els, expect_block=True if mut is MUTATIONS[12] else None)
        assert sum(isinstance(x, w.WireError) for x in m.items) <= 1
        assert read_block(els) is m.block or (read_block(els) is not None and m.block is not None)


def test_real_cmu_frames_bundled_equal_each_frame_alone(data):
    from mocap.datasets import load_trial

    rng = np.random.default_rng(3)
    take = load_trial("35_08")
    miss = np.array([c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "lhand") for c in take.channels])
    for masked in (False, True):
        for k in range(0, 200, 20):
            rows = take.frames[k:k + 16].copy()
            rows[:, miss] = np.nan
            _check_bundle([_element(rng, i, rows.shape[1], masked, r) for i, r in enumerate(rows)], expect_block=True)


def _fill(rng, C, i):
    obs = rng.random(C) > 0.2
    m = w.FillMsg(f"s{i}", int(rng.integers(0, 1 << 62)), float(rng.uniform(0, 2e9)),
                  rng.normal(size=C).astype(np.float32), ~obs, rng.random(C).astype(np.float32),
                  str(rng.choice(w.STATUSES)), "walk", int(rng.integers(0, 1 << 20)))
    if rng.random() < 0.5:
        m.style = rng.dirichlet(np.ones(3)).astype(np.float32)
    if rng.random() < 0.5:
        m.phase = float(rng.random())
    if rng.random() < 0.3:
        m.gap = int(rng.integers(1, 9))
    if rng.random() < 0.2:
        m.positions = rng.normal(size=(4, 3)).astype(np.float32)
    if rng.random() < 0.3:  # rows of a tick's (n, C) arrays, as the scheduler hands them over
        big = rng.normal(size=(3, C)).astype(np.float32)
        m.angles, m.std = big[1], big[2]
    if rng.random() < 0.2:  # a strided column view: written in C order like any other
        m.std = np.asfortranarray(rng.random((C, 2)).astype(np.float32))[:, 1]
    if rng.random() < 0.2:  # arrays not yet float32 / bool: converted the same either way
        m.angles, m.filled = m.angles.astype(np.float64), m.filled.astype(np.uint8)
    return m


def test_a_ticks_answers_packed_in_one_pass_are_the_bytes_of_encoding_each(rng):
    for _ in range(100):
        C = int(rng.choice([1, 7, 62]))
        msgs = []
        for i in range(int(rng.integers(1, 50))):
            r = rng.random()
            msgs.append(_fill(rng, C, i) if r < 0.8 else w.Drop(f"s{i}", i, "conflated") if r < 0.9
                        else w.ErrorMsg("bad_length", "frame field 'angles' must be ...", f"s{i}", i))
        want = w.join_replies([w.encode(m) for m in msgs])
        assert w.replies_of([w.to_map(m) for m in msgs]) == want
        assert w.replies_of([w.to_map(m) for m in msgs], msgpack.Packer(use_bin_type=True).pack) == want
        back = w.decode(want)
        assert isinstance(back, w.Replies) and len(back.items) == len(msgs)
        for m, b in zip(msgs, back.items):
            if isinstance(m, w.FillMsg):
                assert _pack(w.fill_map(m)) == w.encode(m)
                assert np.array_equal(b.angles, np.asarray(m.angles, np.float32))
                assert np.array_equal(b.std, np.asarray(m.std, np.float32))
                assert np.array_equal(b.filled, np.asarray(m.filled, bool))


@pytest.mark.parametrize("n", [1, 64, w.MAX_BUNDLE])
def test_replies_of_a_single_and_a_full_chunk(n):
    msgs = [w.Drop(f"s{i}", i, "late") for i in range(n)]
    assert w.replies_of([w.to_map(m) for m in msgs]) == w.join_replies([w.encode(m) for m in msgs])


def test_no_inf_never_misses_an_infinity(rng):
    from daemon.block import no_inf

    for _ in range(2000):
        a = rng.normal(scale=float(rng.choice([1, 1e30, 1e38])), size=int(rng.integers(1, 80)))
        with np.errstate(over="ignore"):  # values beyond float32 become infinities: wanted here
            a = a.astype(np.float32)
        a[rng.random(a.size) < 0.2] = np.nan
        if rng.random() < 0.5:
            a[rng.integers(a.size)] = rng.choice([np.inf, -np.inf])
        if no_inf(a.tobytes()):
            assert not np.isinf(a).any()
    assert not no_inf(np.array([1, -np.inf], np.float32).tobytes())


def test_huge_observed_values_are_read_by_the_fast_checks(rng):
    """The fast checks sum the observed values (in float64, which float32 values cannot
    overflow): values near the float32 limit are read, as one frame and as a block."""
    big = np.array([3e38, 3e38, np.nan, -3e38], np.float32)
    one = {"stream": "s", "seq": 1, "t": 0.5, "angles": big.tobytes(), "observed": bytes([1, 1, 0, 1])}
    f = w.decode(_pack({"v": 1, "type": "frame", **one}))
    assert f.observed.tolist() == [True, True, False, True] and f.angles[0] == np.float32(3e38)
    m = _check_bundle([one, {**one, "stream": "t"}], expect_block=True)
    assert all(isinstance(x, w.Frame) for x in m.items)
