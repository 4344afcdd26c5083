"""A lone stream's compiled step with its fixed arguments packed in one object
(``hlm.fast.step_slot`` -> ``_step_packed``, a numba structref made once per pool size; issue 19,
bench/notebook/hlm9.md): the same bits as ``_step_slot`` called with the arguments one by one,
every frame, across a pool that grows under the stream (its arrays reallocated: the pack must
follow them) and with the daemon's read-only frames (which take the seam's copying path)."""
from __future__ import annotations

import numpy as np
import pytest

from hlm import fast

pytestmark = pytest.mark.skipif(not fast.enabled() or fast._step_packed is None,
                                reason="numba (with structref) is not installed (or LACUNA_NO_JIT=1)")


@pytest.fixture(scope="module")
def walk(small_walk_hlm):
    from lacuna.modelfile import load_model
    from mocap.datasets import load_trial

    channels = list(load_model(small_walk_hlm).channels)
    test = load_trial("35_08").frames[:240]
    obs = np.ones(test.shape, bool)
    arm = [i for i, c in enumerate(channels) if c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "lhand")]
    obs[30:150, arm] = False
    obs[160:163] = False
    return small_walk_hlm, test, obs


def _unpacked(tables, pool, r, frame, observed, live, live_stats, cond):
    """step_slot's reference: the kernel with its arguments one by one, as before the pack."""
    out, sd, filled, style, phase = fast._step_slot(r, frame, observed, *fast._slot_call(tables, pool, live, live_stats,
                                                                                         cond))
    return out, sd, filled, {"style": style.tolist(), "phase": phase}


@pytest.mark.parametrize("cond", [False, True], ids=["plain", "cond"])
def test_packed_lone_step_is_the_unpacked_kernel_to_the_bit(walk, monkeypatch, cond):
    from lacuna.modelfile import load_model

    path, frames, obs = walk
    a, b = load_model(path), load_model(path)
    from hlm import condfill

    for m in (a, b):  # the conditional correction off, or on with residual covariances of its own
        F = m.representation.n_features
        cov = np.tile(np.eye(F) * 0.5, (m.params.mu.shape[0], 1, 1))
        m.cond = condfill.CondTables(cov, 0.5) if cond else None
    sa, sb = a.stream(), b.stream()
    seen = []
    orig = fast.step_slot
    monkeypatch.setattr(fast, "step_slot", lambda *x, **k: seen.append(x[1].__dict__["_slot_args"][6] if "_slot_args"
                                                                         in x[1].__dict__ else None) or orig(*x, **k))
    for t in range(frames.shape[0]):
        f = np.where(obs[t], frames[t], np.nan)
        o = obs[t]
        if t % 7 == 3:   # as decoded from the wire: read-only (the seam's copying path, then the same kernel)
            fa = a.step_batch([sa], np.frombuffer(f.tobytes()).reshape(1, -1),
                              np.frombuffer(o.tobytes(), dtype=bool).reshape(1, -1))[0]
        else:
            fa = a.step_batch([sa], f[None], o[None].copy())[0]
        monkeypatch.setattr(fast, "step_slot", _unpacked)
        fb = b.step_batch([sb], f[None], o[None].copy())[0]
        monkeypatch.setattr(fast, "step_slot", lambda *x, **k: seen.append(x[1].__dict__["_slot_args"][6]) or orig(*x, **k))
        np.testing.assert_array_equal(fa.frame, fb.frame)
        np.testing.assert_array_equal(fa.std, fb.std)
        np.testing.assert_array_equal(fa.filled, fb.filled)
        np.testing.assert_array_equal(fa.filled, ~o)
        assert fa.extras == fb.extras
        pk = a.pool.__dict__["_slot_args"]   # (the pack the step just used: the pool's own arrays)
        assert pk[0] == a.pool.capacity and pk[5][0] is a.pool.repr["prev_u"] and pk[5][6] is a.pool.core["post"]
        assert isinstance(pk[6], fast.SlotArgs)
        if t == 100:  # the pool grows mid-take: every row's arrays move, the pack must be made again
            grown = [a.stream() for _ in range(a.pool.capacity)] + [b.stream() for _ in range(b.pool.capacity)]
            assert a.pool.capacity == b.pool.capacity == 8 and grown
    assert np.array_equal(a.pool.core["post"][sa.slot], b.pool.core["post"][sb.slot])
    assert len({id(x) for x in seen if x is not None}) == 2   # one pack before the pool grew, one after
