"""``default``'s band_q with its rate gate (blend/withhlm.py, module doc "Band q"): the compiled kernel
(``blend.withhlm_fast.q_band``) on a constructed channel whose gate is worked out here, then the
compiled step against the numpy reference on real takes with real gaps, the fills untouched, and the
persistence (files without band_q load with ones: off)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from blend import withhlm
from blend.withhlm_fast import mix_row, q_band, stream_rate
from lacuna import jit

T = 80
OBS = 40   # frames 0..OBS-1 observed, the rest missing
QB = len(withhlm.Q_EDGES) + 1


def _run(x, M=0.5, gate=None, ref=1.0, bdecay=0.0, qb=0):
    """One angle channel observed as ``x`` for OBS frames, then missing (the blend holds its last value,
    std 1; the HLM says 0, std 1; w 0.5, S 1), band_q M in q bin ``qb``: the std every frame, mb, rst."""
    TB = len(withhlm.T_EDGES) + 1
    W, S = np.full((1, TB, QB), 0.5), np.ones((1, TB))
    k, o, rp, vp, e, wb = np.zeros(1, np.int64), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1)
    out, std, stds, mbs = np.empty(1), np.empty(1), [], []
    rst, mb, buf = np.zeros((4, 1)), np.ones(1), np.zeros(1)
    kM = np.ones((1, QB))
    kM[0, qb] = M
    gpar = np.array([0.0, 0.0, 0.0]) if gate is None else np.array([gate[0], gate[1], 1.0])
    for t in range(T):
        obs = np.array([t < OBS])
        F = np.array([x[min(t, OBS - 1)]])
        mix_row(F, obs, obs, F.copy(), np.ones(1), np.zeros(1), np.ones(1), np.zeros(1), False,
                np.array([True]), np.zeros(1, np.int64), W, S, withhlm.T_EDGES, qb, 0.0, k, o, out, std,
                np.zeros(0), False, 0.0, 0.0, 0.0, rp, vp, e, 0.0, wb)
        q_band(F, obs, np.array([True]), std, k, kM, qb, bdecay, mb, gpar, np.array([ref]), rst,
               math.exp(-1.0 / withhlm.RATE_TAU), True, buf)
        stds.append(std[0])
        mbs.append(mb[0])
    return np.array(stds), np.array(mbs), rst


def _off(x):
    s, _, _ = _run(x, M=1.0)
    return s


@pytest.mark.parametrize("v, gate, factor", [(0.5, None, 0.5), (0.5, (1.0, 2.0), 0.5), (3.0, (1.0, 2.0), 1.0),
                                             (1.5, (1.0, 2.0), 0.75), (1.0, (1.0, 1.0), 0.5), (1.2, (1.0, 1.0), 1.0)])
def test_the_multiplier_is_gated_by_the_streams_rate(v, gate, factor):
    """A channel moving v a frame (ref 1) while observed: in its gap the band is times
    1 + (M - 1) gate, gate 1 at rate <= r0, 0 at >= r1, linear between; ungated: M."""
    x = v * np.arange(OBS, dtype=float)
    s0 = _off(x)
    s1, _, rst = _run(x, M=0.5, gate=gate)
    assert rst[0, 0] / rst[1, 0] == pytest.approx(v, rel=1e-12)
    np.testing.assert_allclose(s1[OBS:], s0[OBS:] * factor, rtol=1e-12)
    np.testing.assert_array_equal(s1[:OBS], s0[:OBS])


def test_the_multiplier_is_low_passed_from_the_gaps_first_frame_and_needs_a_rate():
    x = 0.5 * np.arange(OBS, dtype=float)
    s0 = _off(x)
    bd = math.exp(-1.0 / 12.0)
    s1, mb, _ = _run(x, M=0.5, gate=(1.0, 2.0), bdecay=bd)
    assert mb[OBS] == 0.5                       # the gap's first frame: the target itself
    np.testing.assert_allclose(s1[OBS:], s0[OBS:] * 0.5, rtol=1e-12)   # a steady target stays
    s2, _, _ = _run(x, M=0.5, gate=(1.0, 2.0), ref=0.0)   # no reference: no rate, gate 0
    np.testing.assert_array_equal(s2, s0)
    buf, rst = np.zeros(3), np.zeros((4, 3))
    rst[0], rst[1] = [1.0, 4.0, 9.0], [1.0, 2.0, 0.5]    # rates 1, 2 and (under one value's weight) none
    assert stream_rate(np.array([True, True, True]), np.ones(3), rst, buf) == pytest.approx(1.5)
    assert stream_rate(np.array([False, False, True]), np.ones(3), rst, buf) == -1.0


@pytest.mark.parametrize("bad", [np.zeros((9, 4)), np.full((9, 4), np.nan), np.ones((8, 4))])
def test_a_bad_band_q_is_a_clear_error(bad):
    m = object.__new__(withhlm.WithHLMModel)
    m.group = np.zeros(3, np.int64)
    with pytest.raises(withhlm.FillerError, match="band_q"):
        m.set_band_q(bad)
    with pytest.raises(withhlm.FillerError, match="band_gate"):
        m.set_band_q(np.ones((9, 4)), (2.0, 1.0))


# ---- real takes --------------------------------------------------------------------------------

TRAIN_TAKES = ["35_01", "35_06", "basketball_1"]
SMALL_HLM = {"restarts": 1, "n_iter": 3, "screen_iters": None, "cycle_frames": 140}
FRAMES = 400
M_TEST = np.ones((len(withhlm.GROUP_NAMES), QB))   # every q bin (a small model's stream may never reach q0/q1)
M_TEST[:7] = np.array([[0.4], [0.4], [0.7], [0.8], [0.6], [0.6], [0.6]]) * np.array([1.0, 1.1, 1.2, 1.3])
M_TEST[3, 0] = 1.1


@pytest.fixture(scope="module")
def model(data):
    from mocap import protocols

    ts = protocols.named_training_set(TRAIN_TAKES)
    m = withhlm.train_model(ts, **SMALL_HLM)
    M, gate = withhlm.shipped_band_q()   # train_model applies blend/withhlm.json's band_q and gate
    if M is None:
        assert not m._qon and m.band_gate is None
    else:
        np.testing.assert_array_equal(m.band_q, M)
        assert m._qon == bool((M != 1).any()) and list(m.band_gate) == list(gate)
    return m


@pytest.fixture(scope="module")
def cases(data):
    from mocap import protocols

    got = {c.test: c for c in protocols.Gaps(seed=0, split="test").cases()}
    picked = [got[t] for t in ("35_30", "walking_28", "basketball_5")]
    return [(c.truth[:FRAMES], c.observed[:FRAMES]) for c in picked]


def _fill(model, compiled, M, gate, truth, obs, rate_a=0.0):
    was = dict(model.smooth)
    model.set_smooth(**{**withhlm.SMOOTH, "rate_a": rate_a})
    model.set_band_q(M, gate)
    model.compiled = compiled
    try:
        return model.fill_offline(np.where(obs, truth, np.nan), obs)
    finally:
        model.compiled = jit.enabled()
        model.set_smooth(**was)
        model.set_band_q(np.ones_like(M))


@pytest.mark.realdata
@pytest.mark.skipif(not jit.enabled(), reason="numba does not run here: only the numpy step exists")
@pytest.mark.parametrize("gate, rate_a", [(None, 0.0), ((0.8, 1.5), 0.0), ((0.8, 1.5), 0.5)])
def test_compiled_equals_numpy_and_the_fills_are_unchanged(model, cases, gate, rate_a):
    """With band_q on (gated or not, with the band's rate on or off) the compiled and the numpy mixing
    give the same fills and stds (1e-9); the fills are those of band_q off to the bit."""
    changed = 0
    for truth, obs in cases:
        fa, sa = _fill(model, True, M_TEST, gate, truth, obs, rate_a)
        fb, sb = _fill(model, False, M_TEST, gate, truth, obs, rate_a)
        np.testing.assert_allclose(fa, fb, rtol=0, atol=1e-9)
        np.testing.assert_allclose(sa, sb, rtol=0, atol=1e-9)
        f0, s0 = _fill(model, True, np.ones_like(M_TEST), None, truth, obs, rate_a)
        np.testing.assert_array_equal(fa, f0)
        miss = ~obs & (s0 > 1e-6)
        r = sa[miss] / s0[miss]
        assert r.min() >= M_TEST.min() - 1e-9 and r.max() <= M_TEST.max() + 1e-9
        changed += int((np.abs(r - 1) > 1e-6).sum())
        assert (sa[obs] == 0).all()
    assert changed > 100


@pytest.mark.realdata
def test_band_q_is_saved_and_files_without_it_load_with_ones(model, cases, tmp_path):
    from lacuna import modelfile

    truth, obs = cases[1]
    path = tmp_path / "d.npz"
    model.set_band_q(M_TEST, (0.8, 1.5))
    try:
        model.save(str(path))
    finally:
        model.set_band_q(np.ones_like(M_TEST))
    again = modelfile.load_model(str(path))
    assert np.array_equal(again.band_q, M_TEST) and list(again.band_gate) == [0.8, 1.5]
    given = np.where(obs, truth, np.nan)
    f1, s1 = again.fill_offline(given, obs)
    fm, sm = _fill(model, jit.enabled(), M_TEST, (0.8, 1.5), truth, obs)
    np.testing.assert_allclose(s1, sm, rtol=0, atol=1e-12)
    meta, arrays = modelfile.load_arrays(str(path))
    modelfile.save_arrays(str(tmp_path / "old.npz"), meta,
                          {k: v for k, v in arrays.items() if k not in ("band_q", "band_gate")})
    old = modelfile.load_model(str(tmp_path / "old.npz"))
    assert (old.band_q == 1).all() and old.band_gate is None and not old._qon
    f_old, s_old = old.fill_offline(given, obs)
    f0, s0 = _fill(model, jit.enabled(), np.ones_like(M_TEST), None, truth, obs)
    np.testing.assert_array_equal(f_old, f1)
    np.testing.assert_allclose(s_old, s0, rtol=0, atol=1e-12)
