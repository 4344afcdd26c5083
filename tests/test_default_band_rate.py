"""``default``'s band scaled by the channel's observed rate (blend/withhlm.py, module doc "Rate"):
on the compiled mixing itself (``blend.withhlm_fast.mix_row``, then ``rate_band``) with a constructed channel whose rate
is worked out here, then the compiled step against the numpy reference on real takes with real
gaps, the fills untouched, and the reference's persistence (files without it load with it off)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from blend import withhlm
from blend.withhlm_fast import mix_row, rate_band
from lacuna import jit

T = 80
OBS = 40   # frames 0..OBS-1 observed, the rest missing


def _run(x, a=0.0, ref=1.0, lo=withhlm.RATE_LO, hi=withhlm.RATE_HI, rst=None, n_obs=OBS):
    """One angle channel observed as ``x`` for ``n_obs`` frames, then missing (the blend holds its last
    value, std 1; the HLM says 0, std 1; w 0.5, S 1): the mixing's std every frame, and the rate state."""
    TB, QB = len(withhlm.T_EDGES) + 1, 4
    W, S = np.full((1, TB, QB), 0.5), np.ones((1, TB))
    k, o, rp, vp, e, wb = np.zeros(1, np.int64), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1)
    out, std, stds = np.empty(1), np.empty(1), []
    rst = np.zeros((4, 1)) if rst is None else rst
    rpar = np.array([math.exp(-1.0 / withhlm.RATE_TAU), a, lo, hi])
    one = np.ones(1)
    for t in range(T):
        obs = np.array([t < n_obs])
        F = np.array([x[min(t, n_obs - 1)]])
        mix_row(F, obs, obs, F.copy(), one, np.zeros(1), one, np.zeros(1), False,
                np.array([True]), np.zeros(1, np.int64), W, S, withhlm.T_EDGES, 0, 0.0, k, o, out, std,
                np.zeros(0), False, 0.0, 0.0, 0.0, rp, vp, e, 0.0, wb)
        if a > 0:   # as the model calls it: only where the rate is on
            rate_band(F, obs, np.array([True]), std, rpar, np.array([ref]), rst)
        stds.append(std[0])
    return np.array(stds), rst


def test_off_is_the_band_as_before_and_touches_no_state():
    x = 0.8 * np.arange(OBS, dtype=float)
    s0, rst = _run(x)
    assert (s0[:OBS] == 0).all() and (rst == 0).all()            # a = 0 reads and writes nothing
    hold = x[-1]
    sd = np.sqrt(0.5 + 0.5 + 0.25 * hold * hold)                  # the two-part mixture, w 0.5, diff = -hold
    np.testing.assert_allclose(s0[OBS:], sd, rtol=1e-12)


@pytest.mark.parametrize("v, ref, a, factor", [(0.9, 0.6, 1.0, 1.5), (0.9, 0.6, 0.5, math.sqrt(1.5)),
                                                (3.0, 0.5, 1.0, 2.0), (0.1, 0.8, 1.0, 0.5), (0.3, 0.6, 1.0, 0.5)])
def test_the_band_is_times_the_rate_against_the_reference_clipped(v, ref, a, factor):
    """A channel moving v a frame while observed: in its gap the band is times (v / ref)^a, within
    [RATE_LO, RATE_HI]; the decayed mean of a steady |dx| is that |dx|, whatever the decay."""
    x = v * np.arange(OBS, dtype=float)
    s0, _ = _run(x)
    s1, rst = _run(x, a=a, ref=ref)
    assert rst[0, 0] / rst[1, 0] == pytest.approx(v, rel=1e-12)
    assert rst[3, 0] == 0.0 and rst[2, 0] == x[-1]               # missing now; its last observed value kept
    np.testing.assert_allclose(s1[OBS:], s0[OBS:] * factor, rtol=1e-12)
    np.testing.assert_array_equal(s1[:OBS], s0[:OBS])


def test_the_rate_wraps_angles_and_needs_history():
    """179 -> -179 is a 2-degree step, not 358; with under one value's weight of history (one
    observed frame: no step yet) the factor is 1; a reference of 0 leaves the band alone."""
    x = np.where(np.arange(OBS) % 2 == 0, 179.0, -179.0)
    _, rst = _run(x, a=1.0, ref=2.0)
    assert rst[0, 0] / rst[1, 0] == pytest.approx(2.0, rel=1e-12)
    x = 5.0 + 0.1 * np.arange(OBS)
    s0, _ = _run(x, n_obs=1)
    s1, rst = _run(x, a=1.0, ref=0.01, n_obs=1)
    assert rst[1, 0] == 0.0 and s0[1] > 0
    np.testing.assert_array_equal(s1, s0)
    np.testing.assert_array_equal(_run(x, a=1.0, ref=0.0)[0], _run(x)[0])


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), True])
def test_a_bad_rate_exponent_is_a_clear_error(bad):
    m = object.__new__(withhlm.WithHLMModel)   # set_smooth checks before it sets anything
    with pytest.raises(withhlm.FillerError, match="rate_a"):
        m.set_smooth(knots=False, pop=0.0, rate_a=bad)


# ---- real takes --------------------------------------------------------------------------------

TRAIN_TAKES = ["35_01", "35_06", "basketball_1"]
SMALL_HLM = {"restarts": 1, "n_iter": 3, "screen_iters": None, "cycle_frames": 140}
FRAMES = 400


@pytest.fixture(scope="module")
def model(data):
    from mocap import protocols

    ts = protocols.named_training_set(TRAIN_TAKES)
    m = withhlm.train_model(ts, **SMALL_HLM)
    np.testing.assert_allclose(m.rate_ref, withhlm.rate_ref(ts.sequences, list(m.channels)))
    return m


@pytest.fixture(scope="module")
def cases(data):
    from mocap import protocols

    got = {c.test: c for c in protocols.Gaps(seed=0, split="test").cases()}
    picked = [got[t] for t in ("35_30", "walking_28", "basketball_5")]
    return [(c.truth[:FRAMES], c.observed[:FRAMES]) for c in picked]


def _fill(model, compiled, a, truth, obs):
    was = dict(model.smooth)
    model.set_smooth(**{**withhlm.SMOOTH, "rate_a": a})
    model.compiled = compiled
    try:
        return model.fill_offline(np.where(obs, truth, np.nan), obs)
    finally:
        model.compiled = jit.enabled()
        model.set_smooth(**was)


@pytest.mark.realdata
@pytest.mark.skipif(not jit.enabled(), reason="numba does not run here: only the numpy step exists")
@pytest.mark.parametrize("a", [0.5, 1.0])
def test_compiled_equals_numpy_and_the_fills_are_unchanged(model, cases, a):
    """The compiled mixing and the numpy one give the same fills and stds (1e-9) with the rate on;
    the fills are those of a = 0 to the bit, the band differs inside gaps and stays within the clip."""
    changed = 0
    for truth, obs in cases:
        fa, sa = _fill(model, True, a, truth, obs)
        fb, sb = _fill(model, False, a, truth, obs)
        np.testing.assert_allclose(fa, fb, rtol=0, atol=1e-9)
        np.testing.assert_allclose(sa, sb, rtol=0, atol=1e-9)
        f0, s0 = _fill(model, True, 0.0, truth, obs)
        np.testing.assert_array_equal(fa, f0)
        miss = ~obs & (s0 > 1e-6)
        r = sa[miss] / s0[miss]
        assert r.min() >= withhlm.RATE_LO - 1e-9 and r.max() <= withhlm.RATE_HI + 1e-9
        changed += int((np.abs(r - 1) > 1e-6).sum())
        assert (sa[obs] == 0).all()
    assert changed > 1000


@pytest.mark.realdata
def test_the_reference_is_saved_and_files_without_it_load_with_the_rate_off(model, cases, tmp_path):
    from lacuna import modelfile

    truth, obs = cases[0]
    path = tmp_path / "d.npz"
    was = dict(model.smooth)
    model.set_smooth(**{**withhlm.SMOOTH, "rate_a": 1.0})
    try:
        model.save(str(path))
    finally:
        model.set_smooth(**was)
    again = modelfile.load_model(str(path))
    assert again.smooth["rate_a"] == 1.0 and np.array_equal(again.rate_ref, model.rate_ref)
    given = np.where(obs, truth, np.nan)
    f1, s1 = again.fill_offline(given, obs)
    np.testing.assert_allclose(s1, _fill(model, jit.enabled(), 1.0, truth, obs)[1], rtol=0, atol=1e-12)
    meta, arrays = modelfile.load_arrays(str(path))
    modelfile.save_arrays(str(tmp_path / "old.npz"), meta, {k: v for k, v in arrays.items() if k != "rate_ref"})
    old = modelfile.load_model(str(tmp_path / "old.npz"))
    assert old.rate_ref is None and old.smooth["rate_a"] == 1.0
    f_old, s_old = old.fill_offline(given, obs)
    bq, gate = model.band_q.copy(), model.band_gate
    model.set_band_q(np.ones_like(bq))   # no reference: no rate, so band_q's gate is shut too ("Band q")
    try:
        f0, s0 = _fill(model, jit.enabled(), 0.0, truth, obs)
    finally:
        model.set_band_q(bq, gate)
    np.testing.assert_array_equal(f_old, f1)
    np.testing.assert_allclose(s_old, s0, rtol=0, atol=1e-12)   # no reference: the band as at a = 0, band_q off
    before = {k: v for k, v in meta["smooth"].items() if k != "rate_a"}   # a smooth table before rate_a: off
    modelfile.save_arrays(str(tmp_path / "before.npz"), {**meta, "smooth": before}, arrays)
    assert modelfile.load_model(str(tmp_path / "before.npz")).smooth["rate_a"] == 0.0


def test_a_channel_held_exactly_still_flushes_its_rate_to_zero_not_into_subnormals():
    """A channel that never moves decays its |dx| sum geometrically: after ~85,000 frames (12 minutes
    at 120 Hz) it would be a subnormal float, each operation on which costs ~100x.  Below RATE_FTZ it is
    0, in the compiled kernel and in the numpy path alike (the rate's factor is then its clip's floor
    either way)."""
    from types import SimpleNamespace

    from blend.withhlm_fast import RATE_FTZ

    still = np.full(OBS, 12.5)
    rst = np.array([[RATE_FTZ * 1.2], [120.0], [12.5], [1.0]])    # ~22 frames of decay from the floor
    s1, rst = _run(still, a=1.0, ref=0.5, rst=rst)
    assert rst[0, 0] == 0.0 and rst[1, 0] > 1.0
    s0, _ = _run(still)
    np.testing.assert_allclose(s1[OBS:], s0[OBS:] * withhlm.RATE_LO, rtol=1e-12)
    # the numpy reference, frame by frame from the same state
    rpar = np.array([math.exp(-1.0 / withhlm.RATE_TAU), 1.0, withhlm.RATE_LO, withhlm.RATE_HI])
    me = SimpleNamespace(_rpar=rpar, ang=np.array([True]), _ref=np.array([0.5]))
    st = SimpleNamespace(rst=np.array([[RATE_FTZ * 1.2], [120.0], [12.5], [1.0]]))
    seen = []
    for _ in range(OBS):
        withhlm.WithHLMModel._rate_factor(me, [st], np.array([[12.5]]), np.array([[True]]))
        seen.append(st.rst[0, 0])
    assert seen[-1] == 0.0 and all(v == 0.0 or v >= RATE_FTZ for v in seen)
