"""``default``'s compiled step (WithHLMModel._step_compiled, blend/withhlm.py) equals the numpy
reference (_step's array path and _mix_numpy) frame by frame, on real takes with real gaps.

The compiled step calls the blend's compiled stream step directly (one check of the batch, no
concatenated twin batch) and mixes with blend/withhlm_fast.py; the reference steps the blend
through ``step_batch`` on the streams and twins concatenated and mixes as (n, C) arrays.  Both
see the same shadow windows (their plan is the policy's, WithHLMState._plan), so fills, stds,
frames since onset, anchoring offsets and the shadow evidence q must agree to 1e-9.  Experts
trained small on TRAIN takes (the HLM with one restart and few EM steps); TEST takes scored.
"""
from __future__ import annotations

import numpy as np
import pytest

from blend import withhlm
from blend.withhlm import train_model
from lacuna import jit
from mocap import protocols

pytestmark = [pytest.mark.realdata,
              pytest.mark.skipif(not jit.enabled(), reason="numba does not run here: only the numpy step exists")]

TRAIN_TAKES = ["07_02", "35_01", "35_06", "walking_13", "basketball_1", "soccer_1"]
SMALL_HLM = {"restarts": 1, "n_iter": 4, "screen_iters": None, "cycle_frames": 140}
FRAMES = 400


@pytest.fixture(scope="module")
def model(data):
    ts = protocols.named_training_set(TRAIN_TAKES)
    return train_model(ts, **SMALL_HLM)


@pytest.fixture(scope="module")
def cases(data):
    """Three TEST takes with the gaps protocol's bursts (seed 0), and one of them with nothing
    missing (the shadow check's windows open every 180 frames, the twin steps)."""
    got = {c.test: c for c in protocols.Gaps(seed=0, split="test").cases()}
    picked = [got[t] for t in ("35_30", "walking_28", "basketball_5") if t in got]
    assert len(picked) == 3, sorted(got)
    out = [(c.truth[:FRAMES], c.observed[:FRAMES]) for c in picked]
    out.append((picked[1].truth[:FRAMES], np.ones_like(picked[1].observed[:FRAMES])))
    assert all(len(t) == FRAMES for t, _ in out)
    return out


SMOOTHINGS = {"off": dict(knots=False, pop=0.0), "knots": dict(knots=True, pop=0.0),
              "knots+pop": dict(knots=True, pop=1.0, pop_tau=6.0), "std_knots+pop": dict(knots=False, std_knots=True, pop=2.0),
              "band": dict(knots=False, pop=0.0, band_tau=12.0), "shipped": dict(withhlm.SMOOTH),
              "rate": {**withhlm.SMOOTH, "rate_a": 1.0}}


@pytest.fixture(params=sorted(SMOOTHINGS))
def smoothed(request, model):
    """The model with each smoothing (blend/withhlm.py "Smooth": off, knots, knots and the pop
    limit), restored after."""
    was = dict(model.smooth)
    model.set_smooth(**SMOOTHINGS[request.param])
    yield model
    model.set_smooth(**was)


def _run(model, compiled: bool, streams, truths, masks):
    """Step ``streams`` as one batch through every frame; returns (fills, stds), each (T, n, C)."""
    model.compiled = compiled
    try:
        T = truths.shape[0]
        fills, stds, windows = [], [], 0
        for t in range(T):
            got = model.step_batch(streams, np.where(masks[t], truths[t], np.nan), masks[t])
            fills.append(np.stack([f.frame for f in got]))
            stds.append(np.stack([f.std for f in got]))
            windows += sum(s.sh >= 0 for s in streams)
        return np.array(fills), np.array(stds), windows
    finally:
        model.compiled = jit.enabled()


def _same_state(a, b):
    assert (a.k == b.k).all() and np.allclose(a.o, b.o, rtol=0, atol=1e-9)
    for name in ("rp", "vp", "e", "rst"):   # the pop limit's state, the band's rate
        assert np.allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-9), name
    assert abs(a.logq - b.logq) < 1e-9 and (a.sh, a.sh_n, a.sh_next) == (b.sh, b.sh_n, b.sh_next)
    assert (a.twin is None) == (b.twin is None)


def test_one_stream_compiled_equals_numpy_frame_by_frame(smoothed, cases):
    """One stream (the daemon's usual case) through TEST 35_30's gaps, frame by frame."""
    model = smoothed
    truth, obs = cases[0]
    a, b = model.stream(), model.stream()
    windows = gaps = 0
    try:
        for t in range(len(truth)):
            model.compiled = True
            fa = a.step(truth[t], obs[t])
            model.compiled = False
            fb = b.step(truth[t], obs[t])
            np.testing.assert_allclose(fa.frame, fb.frame, rtol=0, atol=1e-9)
            np.testing.assert_allclose(fa.std, fb.std, rtol=0, atol=1e-9)
            assert (fa.filled == fb.filled).all() and fa.extras["hlm_q"] == pytest.approx(fb.extras["hlm_q"], abs=1e-12)
            windows += a.sh >= 0
            gaps += fa.filled.any()
    finally:
        model.compiled = jit.enabled()
    assert windows > 30 and gaps > 30           # both the gaps and the shadow windows were exercised
    _same_state(a, b)
    assert a.logq != 0.0                        # at least one window closed and moved q


def test_batch_compiled_equals_numpy_and_each_stream_alone(smoothed, cases):
    """Four streams of different takes and masks in one batch: the compiled batch equals the numpy
    batch, and each stream stepped alone (a window of one stream hides nothing from another)."""
    model = smoothed
    truths = np.stack([t for t, _ in cases], 1)           # (T, n, C)
    masks = np.stack([o for _, o in cases], 1)
    sa = [model.stream() for _ in cases]
    sb = [model.stream() for _ in cases]
    fa, da, wa = _run(model, True, sa, truths, masks)
    fb, db, wb = _run(model, False, sb, truths, masks)
    np.testing.assert_allclose(fa, fb, rtol=0, atol=1e-9)
    np.testing.assert_allclose(da, db, rtol=0, atol=1e-9)
    assert wa == wb and wa > 100
    for a, b in zip(sa, sb):
        _same_state(a, b)
    if model.pop > 0:   # the pop limit held something back somewhere (its offsets were exercised)
        assert max(np.abs(s.e).max() for s in sa) > 1e-3
    assert np.isfinite(fa).all() and (~masks).sum() > 1000      # real gaps were filled
    alone = model.stream()
    f1, d1, _ = _run(model, True, [alone], truths[:, 3:4], masks[:, 3:4])
    np.testing.assert_allclose(f1[:, 0], fa[:, 3], rtol=0, atol=1e-9)
    np.testing.assert_allclose(d1[:, 0], da[:, 3], rtol=0, atol=1e-9)


def test_an_observed_nan_is_a_clear_error_and_steps_no_stream(model, cases):
    """The compiled check (withhlm_fast.observed_finite) refuses what checked_batch refuses, with
    its message, before any stream of the batch has stepped."""
    from lacuna.filler import FillerError

    truth, obs = cases[1]
    streams = [model.stream(), model.stream()]
    F = np.where(obs[:2], truth[:2], np.nan)
    model.step_batch(streams, F, obs[:2].copy())
    before = [(s.k.copy(), s.ds.last.copy(), s.sh_n) for s in streams]
    F2 = truth[2:4].copy()
    F2[1, 7] = np.nan
    O2 = np.ones_like(obs[2:4])
    with pytest.raises(FillerError, match="observed values must be finite"):
        model.step_batch(streams, F2, O2)            # NaN where the mask says observed
    for s, (k, last, n) in zip(streams, before):
        assert (s.k == k).all() and np.array_equal(s.ds.last, last) and s.sh_n == n
    O2[1, 7] = False
    got = model.step_batch(streams, F2, O2)          # the streams go on from where they were
    assert len(got) == 2 and np.isfinite(got[0].frame).all()


def test_the_smoothing_is_saved_and_files_without_it_load_as_off(model, cases, tmp_path):
    """train_model gives the shipped choice (blend/withhlm.json); a saved model keeps its smoothing
    and fills as before; a file written before smoothing (no 'smooth') loads with it off, as it
    filled when written; a malformed one is refused by name."""
    from blend import withhlm
    from lacuna import modelfile

    assert model.smooth == {"knots": False, "std_knots": True, "pop": withhlm.POP, "pop_tau": withhlm.POP_TAU,
                            "pop_rel": withhlm.POP_REL, "band_tau": withhlm.BAND_TAU, "rate_a": withhlm.RATE_A,
                            "pace_tau": withhlm.PACE_TAU, "pace_k": withhlm.PACE_K, "pace_a": withhlm.PACE_A}
    assert {**withhlm.SMOOTH_SINCE, **withhlm.shipped()[2]["smooth"]} == model.smooth and model.pop > 0
    truth, obs = cases[0]
    path = tmp_path / "d.npz"
    model.save(str(path))
    again = modelfile.load_model(str(path))
    assert again.smooth == model.smooth
    given = np.where(obs, truth, np.nan)
    np.testing.assert_array_equal(again.fill_offline(given, obs)[0], model.fill_offline(given, obs)[0])
    meta, arrays = modelfile.load_arrays(str(path))
    old = {k: v for k, v in meta.items() if k != "smooth"}
    modelfile.save_arrays(str(tmp_path / "old.npz"), old, arrays)
    legacy = modelfile.load_model(str(tmp_path / "old.npz"))
    assert legacy.smooth == withhlm.NO_SMOOTH and legacy.pop == 0
    assert not np.array_equal(legacy.fill_offline(given, obs)[0], model.fill_offline(given, obs)[0])  # the limit acted
    # a file written before band_tau (its smooth table without it) loads with it off: the same fills, the
    # band's share not low-passed (so a different std where w changed inside a gap)
    before = {k: v for k, v in model.smooth.items() if k != "band_tau"}
    modelfile.save_arrays(str(tmp_path / "before_band.npz"), {**meta, "smooth": before}, arrays)
    pre = modelfile.load_model(str(tmp_path / "before_band.npz"))
    assert pre.smooth == {**model.smooth, "band_tau": 0.0} and pre.bdecay == 0.0 < model.bdecay
    f_pre, s_pre = pre.fill_offline(given, obs)
    f_now, s_now = model.fill_offline(given, obs)
    np.testing.assert_array_equal(f_pre, f_now)
    assert not np.array_equal(s_pre, s_now)
    for bad in ({**withhlm.NO_SMOOTH, "pop": -2.0}, {**withhlm.NO_SMOOTH, "std_knots": 1}, {"pop": 2.0}, "on",
                {**withhlm.NO_SMOOTH, "band_tau": -1.0}, {**withhlm.NO_SMOOTH, "band_tau": float("nan")}):
        modelfile.save_arrays(str(tmp_path / "bad.npz"), {**meta, "smooth": bad}, arrays)
        with pytest.raises(modelfile.ModelFileError, match="smooth"):
            modelfile.load_model(str(tmp_path / "bad.npz"))
