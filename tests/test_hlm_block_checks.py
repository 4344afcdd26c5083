"""HLMModel.step_block's one-call path (the daemon's bundle path, issue 19): the pool rows' checks
made in the compiled call (``hlm.fast._block_rows``) leave the pool untouched when they fail and
raise what FeatureModel.step_block raises; a read-only mask (as the daemon's decoded bundle
gives it) still takes the one call, with step_batch's bits (bench/notebook/hlm64-7.md)."""
from __future__ import annotations

import numpy as np
import pytest

from hlm import fast

pytestmark = pytest.mark.skipif(not fast.enabled(), reason="numba is not installed (or LACUNA_NO_JIT=1)")


@pytest.fixture(scope="module")
def walk(small_walk_hlm):
    from lacuna.modelfile import load_model
    from mocap.datasets import load_trial

    model = load_model(small_walk_hlm)
    channels = list(model.channels)
    test = load_trial("35_08").frames[:200]
    obs = np.ones(test.shape, bool)
    arm = [i for i, c in enumerate(channels) if c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "lhand")]
    obs[30:150, arm] = False
    return model, test, obs


def _pool(model) -> dict[str, bytes]:
    p = model.pool
    return {f"{g}.{k}": v.tobytes() for g, d in (("core", p.core), ("repr", p.repr)) for k, v in d.items()}


def test_read_only_mask_takes_the_one_call_with_step_batchs_bits(walk, monkeypatch):
    model, frames, obs = walk
    a, b = model.with_options(), model.with_options()
    sa = [a.stream() for _ in range(6)][1::2] + [a.stream()]
    sb = [b.stream() for _ in range(6)][1::2] + [b.stream()]
    order = [2, 0, 3, 1]
    offs = np.array([0, 41, 77, 120])
    calls = []
    orig = fast.step_rows_arrays
    monkeypatch.setattr(fast, "step_rows_arrays", lambda *x, **k: calls.append(x[8:]) or orig(*x, **k))
    T = frames.shape[0]
    for t in range(80):
        rows = (offs + t) % T
        o = obs[rows][order]
        f = np.where(o, frames[rows][order], np.nan)
        ro = np.frombuffer(o.tobytes(), dtype=np.bool_).reshape(o.shape)   # read-only, as decoded from the wire
        assert not ro.flags.writeable
        ref = a.step_batch([sa[i] for i in order], f, o)
        got = b.step_block([sb[i] for i in order], f, ro)
        for j, fl in enumerate(ref):
            np.testing.assert_array_equal(got.frame[j], fl.frame)
            np.testing.assert_array_equal(got.std[j], fl.std)
            np.testing.assert_array_equal(got.filled[j], fl.filled)
            assert got.style[j].tolist() == fl.extras["style"] and got.phase[j] == fl.extras["phase"]
    # one call a tick for each path; the block path's asks for the block call's checks and mask
    assert calls.count((True,)) == 80 and len(calls) == 160
    assert _pool(a) == _pool(b)


def test_failed_checks_change_nothing_and_name_the_error(walk):
    model, frames, obs = walk
    m = model.with_options()
    ss = [m.stream() for _ in range(4)]
    f = np.where(obs[:4], frames[:4], np.nan)
    for _ in range(5):
        m.step_block(ss, f, obs[:4].copy())
    before = _pool(m)
    with pytest.raises(ValueError, match="same stream twice"):
        m.step_block([ss[0], ss[1], ss[0]], f[:3], obs[:3].copy())
    assert _pool(m) == before
    tabs = m._slot_tables
    assert fast.step_rows_arrays(tabs, m.pool, np.array([1, 2, 1]), f[:3], obs[:3].copy(), block=True) is None
    assert _pool(m) == before
    for bad in ([0, m.pool.capacity], [-1, 0]):
        with pytest.raises(IndexError, match="pool rows"):
            fast.step_rows_arrays(tabs, m.pool, np.array(bad), f[:2], obs[:2].copy())
        assert fast.step_rows_arrays(tabs, m.pool, np.array(bad), f[:2], obs[:2].copy(), block=True) is None
        assert _pool(m) == before
    got = m.step_block(ss, f, obs[:4].copy())                                # and the streams step on
    assert np.isfinite(got.frame).all() and _pool(m) != before
