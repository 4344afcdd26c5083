"""``default``'s pace (blend/withhlm.py, module doc "Pace"): the compiled kernel
(``blend.withhlm_fast.pace_row``) on constructed channels whose pace is worked out here (a body that
stops stops the fill; a body that moves on moves it on; the gap starts at the last value), then the
compiled step against the numpy reference on real takes with real gaps, off = the fills without it to
the bit, and files without the keys load with it off."""
from __future__ import annotations

import math

import numpy as np
import pytest

from blend import withhlm
from blend.withhlm_fast import pace_row
from lacuna import jit

OBS = 60    # the filled channel is observed for frames 0..OBS-1, then missing
STOP = 120  # the observed body moves 1 a frame until STOP, then holds still
GO = 300    # ... and moves on from here
T = 420


def _run(tau=15.0, k=1.0, a=0.0, y_step=0.5):
    """Channels 0, 1: the observed body (angles, ref 1), moving 1 a frame, still over [STOP, GO), then
    moving again.  Channel 2: observed (moving y_step a frame) until OBS, then missing, the fill
    before the pace (``out`` as the mixing left it) going on at y_step a frame.  The paced fill every
    frame and the pace's state."""
    ang, ref = np.ones(3, bool), np.ones(3)
    ps, pz, py, pr, buf = np.zeros((6, 3)), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3)
    k_since = np.zeros(3, np.int64)
    ppar = np.array([math.exp(-1.0 / tau), math.exp(-1.0 / withhlm.RATE_TAU), k, a])
    body = np.cumsum([0.0] + [0.0 if STOP <= t < GO else 1.0 for t in range(1, T)])
    fills, ys = [], []
    for t in range(T):
        y = y_step * t
        F = np.array([body[t], -body[t], y if t < OBS else np.nan])
        O = np.array([True, True, t < OBS])
        k_since[2] = 0 if t < OBS else k_since[2] + 1   # as mix_row counts it
        out = np.where(O, F, y)
        pace_row(F, O, ang, out, k_since, ref, ps, pz, py, pr, ppar, buf)
        fills.append(out[2])
        ys.append(y)
    return np.array(fills), np.array(ys), pr


def test_a_body_moving_at_its_pace_leaves_the_fill_as_it_is_and_the_gap_starts_at_the_last_value():
    z, y, pr = _run()
    np.testing.assert_allclose(z[:STOP], y[:STOP], rtol=0, atol=1e-9)   # the body's rate = its onset rate: s = 1
    assert pr[2] == pytest.approx(1.0, rel=1e-9)                         # the slow rate at the onset
    assert z[OBS] - z[OBS - 1] == pytest.approx(0.5)                     # the first filled frame: last value + its step


def test_a_stopped_body_stops_the_fill_and_a_body_moving_on_moves_it_on():
    z, y, _ = _run()
    step = np.diff(z)
    fd = math.exp(-1.0 / 15.0)
    # n frames still from STOP: the fast rate (its count at its steady 1 / (1 - fd)) is fd^n of the onset's,
    # so is the pace; the step into frame t is step[t - 1]
    for n in (15, 45, 90):
        assert step[STOP + n - 2] == pytest.approx(0.5 * fd ** n, rel=1e-3)
    assert z[GO - 1] - z[STOP] < 0.5 * 15 * 1.01      # it moved at most ~tau frames' worth while the body stood
    assert y[GO - 1] - y[STOP] == pytest.approx(0.5 * (GO - 1 - STOP))
    # n frames moving again from GO: the fast rate is back to 1 - fd^n of the onset's, and so the fill's step
    for n in (5, 30, 110):
        assert step[GO + n - 2] == pytest.approx(0.5 * (1.0 - fd ** n), rel=1e-3)
    assert np.all(step >= -1e-12)                     # never backwards: only the fill's own steps, scaled


def test_a_level_paces_only_a_body_slower_than_it_and_off_is_untouched():
    za, ya, _ = _run(a=0.25)          # onset rate 1: the reference is min(1, 0.25) = 0.25
    z1, _, _ = _run(a=0.0)
    step_a, step_1 = np.diff(za), np.diff(z1)
    n = int(np.argmax(step_1[STOP:] < 0.5 * 0.99))   # the frame the pace against the onset starts to bite
    assert step_a[STOP + n] == pytest.approx(0.5)     # ... where the level's pace is still 1
    assert step_a[STOP + 60] < 0.5 and (step_a[STOP:GO - 1] >= step_1[STOP:GO - 1] - 1e-12).all()


# ---- real takes --------------------------------------------------------------------------------

TRAIN_TAKES = ["35_01", "35_06", "basketball_1"]
SMALL_HLM = {"restarts": 1, "n_iter": 3, "screen_iters": None, "cycle_frames": 140}
FRAMES = 500


@pytest.fixture(scope="module")
def model(data):
    from mocap import protocols

    ts = protocols.named_training_set(TRAIN_TAKES)
    m = withhlm.train_model(ts, **SMALL_HLM)
    assert m.smooth["pace_tau"] == 0.0 and not m._pace_on   # shipped: off
    return m


@pytest.fixture(scope="module")
def cases(data):
    from mocap import protocols

    got = {c.test: c for c in protocols.Gaps(seed=0, split="test").cases()}
    return [(got[t].truth[:FRAMES], got[t].observed[:FRAMES]) for t in ("49_20", "walking_28", "basketball_5")]


def _fill(model, compiled, truth, obs, **pace):
    was = dict(model.smooth)
    model.set_smooth(**{**was, **pace})
    model.compiled = compiled
    try:
        return model.fill_offline(np.where(obs, truth, np.nan), obs)
    finally:
        model.compiled = jit.enabled()
        model.set_smooth(**was)


@pytest.mark.realdata
@pytest.mark.skipif(not jit.enabled(), reason="numba does not run here: only the numpy step exists")
@pytest.mark.parametrize("pace", [{"pace_tau": 15.0, "pace_k": 1.0, "pace_a": 0.0},
                                  {"pace_tau": 40.0, "pace_k": 1.0, "pace_a": 0.5}])
def test_compiled_equals_numpy_the_band_is_unchanged_and_off_is_the_old_fill(model, cases, pace):
    changed = 0
    for truth, obs in cases:
        fa, sa = _fill(model, True, truth, obs, **pace)
        fb, sb = _fill(model, False, truth, obs, **pace)
        np.testing.assert_allclose(fa, fb, rtol=0, atol=1e-9)
        np.testing.assert_allclose(sa, sb, rtol=0, atol=1e-9)
        f0, s0 = _fill(model, True, truth, obs, pace_tau=0.0)
        np.testing.assert_array_equal(sa, s0)            # the band is not the pace's
        np.testing.assert_array_equal(fa[obs], f0[obs])  # observed values pass through
        changed += int((np.abs(fa - f0) > 1e-6).sum())
        fo, _ = _fill(model, False, truth, obs, pace_tau=0.0)
        np.testing.assert_allclose(fo, f0, rtol=0, atol=1e-9)
    assert changed > 100


@pytest.mark.realdata
def test_pace_is_saved_and_files_without_it_load_with_it_off(model, cases, tmp_path):
    from lacuna import modelfile

    truth, obs = cases[0]
    pace = {"pace_tau": 15.0, "pace_k": 1.0, "pace_a": 0.25}
    was = dict(model.smooth)
    model.set_smooth(**{**was, **pace})
    try:
        model.save(str(tmp_path / "d.npz"))
    finally:
        model.set_smooth(**was)
    again = modelfile.load_model(str(tmp_path / "d.npz"))
    assert {k: again.smooth[k] for k in pace} == pace and again._pace_on
    given = np.where(obs, truth, np.nan)
    np.testing.assert_allclose(again.fill_offline(given, obs)[0], _fill(model, jit.enabled(), truth, obs, **pace)[0],
                               rtol=0, atol=1e-12)
    meta, arrays = modelfile.load_arrays(str(tmp_path / "d.npz"))
    meta["smooth"] = {k: v for k, v in meta["smooth"].items() if k not in pace}   # a file written before the pace
    modelfile.save_arrays(str(tmp_path / "old.npz"), meta, arrays)
    old = modelfile.load_model(str(tmp_path / "old.npz"))
    assert old.smooth["pace_tau"] == 0.0 and not old._pace_on
    np.testing.assert_array_equal(old.fill_offline(given, obs)[0], _fill(model, jit.enabled(), truth, obs, pace_tau=0.0)[0])


def test_bad_pace_settings_are_a_clear_error():
    m = object.__new__(withhlm.WithHLMModel)
    m.rate_ref = None
    for bad in ({"pace_tau": -1.0}, {"pace_tau": float("nan")}, {"pace_tau": 10.0, "pace_k": 0.0}, {"pace_a": -0.1}):
        with pytest.raises(withhlm.FillerError, match="pace"):
            m.set_smooth(knots=False, pop=0.0, **bad)
