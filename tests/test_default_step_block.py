"""blend's ``default`` (blend/withhlm.py) has its own ``step_block``: the compiled mixing writes
each stream's fill and std straight into (n, C) rows, the blend's into scratch rows, the HLM's
through its own ``step_block``, with no Fill per stream.  Against ``step_batch``'s Fills stacked
(``Model.step_block``, what the daemon's bundle path did before), on real CMU frames (35_08, the
left arm lost in bursts and now and then most channels): two sets of streams of one model, stepped
in lockstep, must give the same bytes every frame (fills, std, filled, style posteriors, phases)
and end in the same stream states; the array path is the one that ran."""
from __future__ import annotations

import numpy as np
import pytest

from lacuna.filler import BlockFill, Model

pytestmark = pytest.mark.realdata
ARM = ("lhumerus", "lradius", "lwrist", "lhand")


@pytest.fixture(scope="module")
def default(data):
    from tests.test_daemon_wire_block_hlm import _default

    return _default()


def _frames(n, T, seed):
    from mocap.datasets import load_trial

    take = load_trial("35_08")
    x = take.frames
    arm = np.array([c.split(".")[0] in ARM for c in take.channels])
    rng = np.random.default_rng(seed)
    for k in range(T):
        rows = (k + 37 * np.arange(n)) % len(x)
        obs = np.ones((n, x.shape[1]), bool)
        lost = ((k + 13 * np.arange(n)) // 50) % 3 == 1  # the arm lost 50 frames in 150, streams out of phase
        obs[lost[:, None] & arm[None, :]] = False
        few = rng.random(n) < 0.03  # now and then nothing but a few channels
        obs[few] &= rng.random((int(few.sum()), x.shape[1])) < 0.3
        yield np.where(obs, x[rows], np.nan), obs


def _state_bytes(s):
    out = [s.k.tobytes(), s.o.tobytes(), s.logq, s.sh, s.sh_n, s.n_win, s.eh, s.e0, s.lr_n, s.twin is None]
    out += [v.tobytes() for v in vars(s.ds).values() if isinstance(v, np.ndarray)]
    return out


@pytest.mark.parametrize("n", [1, 6])
def test_default_step_block_is_step_batch_as_arrays(default, n, monkeypatch):
    model = default
    assert model.compiled, "the compiled mixing (numba) is what the array step is for"
    ran = {"block": 0}
    orig = type(model)._step_block
    monkeypatch.setattr(type(model), "_step_block", lambda self, *a: ran.__setitem__("block", ran["block"] + 1)
                        or orig(self, *a))
    sa, sb = [model.stream() for _ in range(n)], [model.stream() for _ in range(n)]
    windows = 0
    for k, (f, o) in enumerate(_frames(n, 420, seed=n)):
        a = Model.step_block(model, sa, f, o)  # (the base class's: step_batch's Fills stacked)
        b = model.step_block(sb, f.copy(), o.copy())
        assert isinstance(b, BlockFill)
        for x, y in ((a.frame, b.frame), (a.std, b.std)):
            assert x.dtype == y.dtype == np.float64 and x.tobytes() == y.tobytes(), k
        assert a.filled.tobytes() == b.filled.tobytes()
        sta = np.array(a.style, np.float32).tobytes()
        assert sta == np.ascontiguousarray(b.style, np.float32).tobytes(), k
        pa = [float("nan") if p is None else p for p in a.phase]
        pb = [float("nan") if p is None else p for p in (b.phase.tolist() if isinstance(b.phase, np.ndarray) else b.phase)]
        assert np.array_equal(pa, pb, equal_nan=True), k
        for x, y in zip(sa, sb):
            assert _state_bytes(x) == _state_bytes(y), k
        windows += sum(s.sh >= 0 for s in sb)
    assert ran["block"] == 420
    assert windows > 0  # shadow windows opened (the twins stepped into their scratch rows)
    assert any(s.n_win > 0 for s in sb)  # and were scored: the HLM's share in play
