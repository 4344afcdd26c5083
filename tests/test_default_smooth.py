"""``default``'s smoothing (blend/withhlm.py, module doc "Smooth") on the compiled mixing itself,
``blend.withhlm_fast.mix_row``, with constructed experts whose answers are worked out here: the
pop limit holds back a jump of the HLM's fill inside a gap and lets it in over a few frames,
leaves a fill that moves smoothly alone, and is the unsmoothed mixing bit for bit when off; the
knots read W between the time bins' centres.  (Compiled against numpy on real takes, and the
setting's persistence: tests/test_default_step_equal.py.)"""
from __future__ import annotations

import numpy as np
import pytest

from blend import withhlm
from blend.withhlm_fast import mix_row

T = 60
JUMP_AT = 25   # the HLM's fill jumps by 14 degrees on this frame (as its phase did on VALIDATION's walking_21)


def _run(H, w=0.9, knots=False, pop=0.0, prel=0.0, tau=3.0, W=None, S=None, wk=None, band_tau=0.0, hsd=1.0):
    """One channel missing from frame 1 on: the blend holds 0 (std 1), the HLM says ``H[t]`` (std 1);
    the mixing's fill and std for every frame (anchoring off, so the fill is w H from the gap's
    first frame on).  ``wk``: W between the knots too (default: as ``knots``)."""
    TB, QB = len(withhlm.T_EDGES) + 1, 4
    Wt = np.full((1, TB, QB), w) if W is None else W
    S = np.ones((1, TB)) if S is None else S
    wk = knots if wk is None else wk
    k, o, rp, vp, e = np.zeros(1, np.int64), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1)
    out, std, fills, stds = np.empty(1), np.empty(1), [], []
    kn = withhlm.T_KNOTS if knots else np.zeros(0)
    pdecay = float(np.exp(-1.0 / tau)) if pop > 0 else 0.0
    one = np.ones(1)
    bdecay = float(np.exp(-1.0 / band_tau)) if band_tau > 0 else 0.0
    wb = np.zeros(1)
    for t in range(T):
        obs = np.array([t == 0])
        mix_row(np.zeros(1), obs, obs, np.zeros(1), one, np.array([H[t]]), np.array([hsd]), np.zeros(1), False,
                np.array([True]), np.zeros(1, np.int64), Wt, S, withhlm.T_EDGES, 0, 0.0, k, o, out, std,
                kn, wk, pop, prel, pdecay, rp, vp, e, bdecay, wb)
        fills.append(out[0])
        stds.append(std[0])
    return np.array(fills), np.array(stds)


def _ramp_then_jump():
    H = 0.5 * np.arange(T, dtype=float)      # the HLM moves 0.5 degree a frame
    H[JUMP_AT:] += 14.0
    return H


def test_off_is_the_unsmoothed_fill_and_the_pop_shows():
    H = _ramp_then_jump()
    f = _run(H)[0]
    np.testing.assert_array_equal(f[1:], 0.9 * H[1:])   # D + w (H - D), D = 0: bit for bit
    assert f[JUMP_AT] - f[JUMP_AT - 1] == pytest.approx(0.9 * 14.5)


def test_the_pop_limit_holds_a_jump_back_and_lets_it_in_over_a_few_frames():
    H = _ramp_then_jump()
    off, on = _run(H)[0], _run(H, pop=2.0, prel=1.0, tau=3.0)[0]
    np.testing.assert_array_equal(on[:JUMP_AT], off[:JUMP_AT])   # a steady course is never limited
    step = 0.45                                                  # the fill's own step before the jump
    # the jump frame moves at most the course's step plus pop + prel |step|
    assert on[JUMP_AT] - on[JUMP_AT - 1] == pytest.approx(step + 2.0 + 1.0 * step)
    held = off[JUMP_AT] - on[JUMP_AT]
    assert held == pytest.approx(0.9 * 14 - 2.0 - step)
    # what was held back decays by exp(-1/3) a frame: every later step is far below the pop's 12.6
    d = np.diff(on[JUMP_AT:])
    assert d.max() < 0.9 * 14 / 3 and (d > 0).all()
    assert abs(on[JUMP_AT + 2] - off[JUMP_AT + 2]) == pytest.approx(held * np.exp(-2 / 3), rel=1e-9)
    assert abs(on[-1] - off[-1]) < 1e-3 * held                   # and it is let in: the fill comes back to the mix


def test_the_first_two_frames_of_a_gap_are_never_limited():
    # the HLM's course starts with a fast step (the mixing's first frames set the course, not judge it)
    H = np.concatenate([[0.0, 0.0, 10.0], 10.0 + 0.1 * np.arange(T - 3)])
    np.testing.assert_array_equal(_run(H, pop=2.0, prel=1.0)[0][:3], _run(H)[0][:3])


def test_the_knots_read_w_between_the_bins_centres():
    TB = len(withhlm.T_EDGES) + 1
    W = np.zeros((1, TB, 4))
    W[0, :, 0] = np.linspace(0.0, 0.7, TB)     # a share that grows bin by bin
    H = np.full(T, 10.0)
    steps, smooth = _run(H, W=W)[0], _run(H, W=W, knots=True)[0]
    kk = np.arange(1, T)                        # frames since onset of frames 1..T-1
    tb = np.searchsorted(withhlm.T_EDGES, kk, side="right")
    np.testing.assert_allclose(steps[1:], 10.0 * W[0, tb, 0])
    np.testing.assert_allclose(smooth[1:], 10.0 * np.interp(kk, withhlm.T_KNOTS, W[0, :, 0]), rtol=0, atol=1e-12)
    # the steps at the bin edges are gone: the largest step of the knotted fill is far below the binned one's
    assert np.abs(np.diff(smooth[1:])).max() < 0.5 * np.abs(np.diff(steps[1:])).max()


def test_std_knots_smooth_the_band_alone():
    TB = len(withhlm.T_EDGES) + 1
    S = np.linspace(1.0, 3.0, TB)[None, :]      # a std scale that grows bin by bin
    W = np.zeros((1, TB, 4))
    W[0, :, 0] = np.linspace(0.0, 0.7, TB)
    H = np.full(T, 10.0)
    f0, s0 = _run(H, W=W, S=S)
    f1, s1 = _run(H, W=W, S=S, knots=True, wk=False)          # the band between the knots, W in steps
    np.testing.assert_array_equal(f1, f0)                        # the fill is untouched
    kk = np.arange(1, T)
    tb = np.searchsorted(withhlm.T_EDGES, kk, side="right")
    w = W[0, tb, 0]
    sd = np.sqrt((1 - w) + w + w * (1 - w) * 100.0)              # the two-part mixture, both stds 1, diff 10
    np.testing.assert_allclose(s0[1:], S[0, tb] * sd, rtol=1e-12)
    np.testing.assert_allclose(s1[1:], np.interp(kk, withhlm.T_KNOTS, S[0]) * sd, rtol=1e-12)


@pytest.mark.parametrize("bad", [dict(knots=1, pop=0.0), dict(knots=False, pop=-1.0), dict(knots=False, pop=float("nan")),
                                 dict(knots=False, pop=2.0, pop_tau=0.0), dict(knots=False, pop=2.0, pop_rel=True),
                                 dict(knots=False, pop=0.0, std_knots="yes")])
def test_a_bad_smoothing_is_a_clear_error(bad):
    m = object.__new__(withhlm.WithHLMModel)   # set_smooth checks before it sets anything
    with pytest.raises(withhlm.FillerError, match="smooth"):
        m.set_smooth(**bad)


def test_the_band_bends_where_w_steps_and_the_fill_keeps_its_w():
    """W steps from 0.2 to 0.9 at a time bin's edge inside the gap; the HLM's std is 4x the blend's.
    Without band_tau the std jumps there in one frame; with it the std's share follows w over ~12
    frames: no frame's std moves more than a quarter of the jump, it gets there within 5 tau, and the
    fill is the same bit for bit."""
    TB, QB = len(withhlm.T_EDGES) + 1, 4
    edge = int(withhlm.T_EDGES[1])          # frames since onset where the second bin ends
    assert 3 < edge < T - 20
    W = np.full((1, TB, QB), 0.9)
    W[0, :2] = 0.2
    H = np.full(T, 5.0)
    f0, s0 = _run(H, W=W, hsd=4.0)
    f1, s1 = _run(H, W=W, hsd=4.0, band_tau=12.0)
    np.testing.assert_array_equal(f0, f1)
    np.testing.assert_array_equal(s0[:edge], s1[:edge])       # before the step: the same band
    jump = s0[edge] - s0[edge - 1]
    assert jump > 1.0                                           # the unsmoothed band steps ...
    steps = np.diff(s1[edge - 1:])
    assert np.all(np.abs(steps) <= 0.25 * jump)                 # ... the smoothed one bends
    assert abs(s1[min(edge + 60, T - 1)] - s0[min(edge + 60, T - 1)]) <= 0.05 * jump
    assert s1[edge + 1] > s1[edge] > s1[edge - 1]               # and moves toward it at once
