"""mocap.metrics on hand-made arrays whose answers are worked out here (issue 17): gap runs,
the first-frame and time-since-onset bins, gap-length bins, onset against the truth's step and
hold, calibration shares, the Gaussian NLL against scipy, root position in cm, pooling."""
import numpy as np
import pytest
from scipy.stats import norm

from mocap import metrics
from mocap.protocols import GAP_GROUPS, Case


def _case(truth, observed, channels, fps=100.0, scored=None, cm=None):
    truth = np.asarray(truth, float)
    scored = np.array([metrics.is_angle(c) for c in channels]) if scored is None else scored
    return Case("t", "p", truth, np.asarray(observed, bool), list(channels), fps, scored, {"cm_per_unit": cm})


def _fig(summary, name):
    (v,) = [v for m, v, n in summary if m == name]
    return v


def test_gap_structure_counts_runs_per_channel():
    miss = np.array([[0, 1], [1, 1], [1, 0], [0, 0], [1, 1]], bool)
    since, length, start = metrics.gap_structure(miss)
    assert since[:, 0].tolist() == [-1, 0, 1, -1, 0]
    assert length[:, 0].tolist() == [0, 2, 2, 0, 1]
    assert start[:, 0].tolist() == [-1, 1, 1, -1, 4]
    assert since[:, 1].tolist() == [0, 1, -1, -1, 0]
    assert length[:, 1].tolist() == [2, 2, 0, 0, 1]


def _ramp_case(offset):
    """One angle channel rising 1 degree a frame at 100 Hz, erased for 30 frames from frame 10;
    the fill is the truth plus ``offset`` there.  Hold's error at gap frame k is -(k + 1)."""
    T = 60
    truth = np.arange(T, dtype=float)[:, None]
    obs = np.ones((T, 1), bool)
    obs[10:40] = False
    case = _case(truth, obs, ["lfemur.rx"])
    fill = np.where(obs, truth, truth + offset)
    return case, fill


def test_first_frame_and_time_since_onset_bins():
    case, _ = _ramp_case(0.0)
    hold = np.where(case.observed, case.truth, 9.0)  # frame 9's value held: error -(k+1) at gap frame k
    s = metrics.summarise(metrics.values(case, hold, None, GAP_GROUPS))
    k = np.arange(30)
    e = k + 1.0
    rms = lambda sel: np.sqrt(np.mean(e[sel] ** 2))  # noqa: E731
    assert _fig(s, "rms_deg[since first]") == pytest.approx(1.0)
    assert _fig(s, "rms_deg[since 0-0.05s]") == pytest.approx(rms((k >= 1) & (k < 5)))  # 10-40 ms, disjoint from the first
    assert _fig(s, "rms_deg[since 0.05-0.1s]") == pytest.approx(rms((k >= 5) & (k < 10)))
    assert _fig(s, "rms_deg[since 0.1-0.25s]") == pytest.approx(rms((k >= 10) & (k < 25)))
    assert _fig(s, "rms_deg[since 0.25-0.5s]") == pytest.approx(rms(k >= 25))
    assert not [m for m, _, _ in s if m.startswith("rms_deg[since 0.5")]  # empty bins are left out
    # a 0.3 s gap: every value falls in the 0.25-0.5 s length bin
    assert _fig(s, "rms_deg[len 0.25-0.5s]") == pytest.approx(rms(k >= 0))
    assert [m for m, _, _ in s if m.startswith("rms_deg[len")] == ["rms_deg[len 0.25-0.5s]"]
    assert _fig(s, "rms_deg[group left-leg]") == pytest.approx(rms(k >= 0))
    # the fill is hold itself: its first 100 ms equal hold's, and its onset error equals the step
    assert _fig(s, "rms_deg[first 0.1s]") == pytest.approx(rms(k < 10))
    assert _fig(s, "hold_rms_deg[first 0.1s]") == pytest.approx(rms(k < 10))
    assert _fig(s, "onset_err_over_step") == pytest.approx(1.0)


def test_onset_compares_the_first_error_with_the_truths_step_and_hold():
    case, fill = _ramp_case(2.0)  # off by 2 degrees from the first erased frame on
    s = metrics.summarise(metrics.values(case, fill, None, GAP_GROUPS))
    assert _fig(s, "onset_err_median_deg") == pytest.approx(2.0)
    assert _fig(s, "onset_truth_step_median_deg") == pytest.approx(1.0)
    assert _fig(s, "onset_err_over_step") == pytest.approx(2.0)
    assert _fig(s, "rms_deg[first 0.1s]") == pytest.approx(2.0)
    assert _fig(s, "hold_rms_deg[first 0.1s]") == pytest.approx(np.sqrt(np.mean(np.arange(1, 11) ** 2.0)))


def test_angle_errors_wrap_and_translations_are_not_scored_as_angles():
    truth = np.array([[179.0, 5.0], [179.0, 5.0], [-179.0, 5.0]])
    obs = np.array([[1, 1], [0, 0], [0, 0]], bool)
    case = _case(truth, obs, ["root.ry", "root.tx"], cm=1.0)
    fill = np.array([[179.0, 5.0], [-179.0, 5.0], [179.0, 5.0]])
    s = metrics.summarise(metrics.values(case, fill, None, GAP_GROUPS))
    assert _fig(s, "rms_deg") == pytest.approx(2.0)  # 358 degrees apart is 2 degrees
    assert metrics.values(case, fill, None, GAP_GROUPS).err.size == 2  # root.tx is not an angle value


def test_within_k_std_shares_and_the_std_floor():
    T = 5
    truth = np.zeros((T, 1))
    obs = np.ones((T, 1), bool)
    obs[1:] = False
    case = _case(truth, obs, ["lhumerus.rx"])
    fill = np.array([[0.0], [0.5], [-1.5], [2.5], [0.05]])
    std = np.array([[0.0], [1.0], [1.0], [1.0], [0.01]])  # the last is below the 0.1 degree floor
    s = metrics.summarise(metrics.values(case, fill, std, GAP_GROUPS))
    # |err|/std: 0.5, 1.5, 2.5 and 0.05/max(0.01, 0.1) = 0.5
    assert _fig(s, "within_1std") == pytest.approx(2 / 4)
    assert _fig(s, "within_2std") == pytest.approx(3 / 4)
    assert metrics.STD_FLOOR == 0.1


def test_nll_matches_scipy_norm_logpdf(rng):
    n = 200
    err = rng.normal(0, 3, n)
    std = rng.uniform(0.5, 5, n)
    std[:10] = 0.02  # floored to 0.1
    got = metrics.gaussian_nll(err, std)
    want = -norm.logpdf(err, loc=0.0, scale=np.maximum(std, metrics.STD_FLOOR))
    assert np.allclose(got, want)
    truth = np.zeros((n + 1, 1))
    obs = np.ones((n + 1, 1), bool)
    obs[1:] = False
    case = _case(truth, obs, ["lhumerus.rx"])
    fill = np.concatenate([[0.0], err])[:, None]
    s = metrics.summarise(metrics.values(case, fill, np.concatenate([[0.0], std])[:, None], GAP_GROUPS))
    assert _fig(s, "nll_per_value") == pytest.approx(np.mean(want))


def test_calibration_is_na_when_no_std_is_reported():
    case, fill = _ramp_case(1.0)
    s = metrics.summarise(metrics.values(case, fill, np.zeros_like(fill), GAP_GROUPS))
    assert _fig(s, "within_1std") is None and _fig(s, "within_2std") is None and _fig(s, "nll_per_value") is None
    assert _fig(s, "rms_deg") == pytest.approx(1.0)  # the error itself is still scored


def test_root_translation_error_in_cm_where_the_root_is_erased():
    T = 6
    ch = ["root.tx", "root.ty", "root.tz", "root.rx"]
    truth = np.zeros((T, 4))
    truth[:, 0] = 10.0 * np.arange(T)  # 10 units a frame along x
    obs = np.ones((T, 4), bool)
    obs[2:5, :3] = False  # frames 2-4: root translation erased
    cm = metrics.cm_per_unit(type("S", (), {"units": {"length": "0.45"}})())
    assert cm == pytest.approx(2.54 / 0.45)
    case = _case(truth, obs, ch, cm=cm)
    fill = truth.copy()
    fill[2:5, 0] = truth[2:5, 0] - 3.0  # 3 units behind
    fill[2:5, 1] = 4.0  # and 4 units up: 5 units away
    s = metrics.summarise(metrics.values(case, fill, None, GAP_GROUPS))
    assert _fig(s, "root_pos_rms_cm") == pytest.approx(5.0 * cm)
    assert _fig(s, "root_pos_max_cm") == pytest.approx(5.0 * cm)
    # hold keeps x at 10 (frame 1): 10, 20 and 30 units behind
    assert _fig(s, "hold_root_pos_rms_cm") == pytest.approx(np.sqrt(np.mean(np.array([10, 20, 30.0]) ** 2)) * cm)
    case.info["cm_per_unit"] = None  # no ASF: the file's own units, named so
    s = metrics.summarise(metrics.values(case, fill, None, GAP_GROUPS))
    assert _fig(s, "root_pos_rms_units") == pytest.approx(5.0)


def test_cmu_asf_length_unit_is_one_over_045_inch(data):
    from mocap.asf import read_asf

    sk = read_asf(data / "cmu" / "07" / "07.asf")
    assert sk.units["length"] == "0.45"
    assert metrics.cm_per_unit(sk) == pytest.approx(5.6444, abs=1e-4)  # CMU FAQ: (1/0.45) * 2.54 / 100 m


def test_pooling_is_over_values_not_a_mean_of_figures():
    a, fa = _ramp_case(1.0)  # 30 values off by 1
    T = 20
    truth = np.zeros((T, 1))
    obs = np.ones((T, 1), bool)
    obs[5:15] = False  # 10 values off by 4
    b = _case(truth, obs, ["lfemur.rx"])
    fb = np.where(obs, truth, 4.0)
    va, vb = metrics.values(a, fa, None, GAP_GROUPS), metrics.values(b, fb, None, GAP_GROUPS)
    pooled = metrics.summarise(metrics.Values.concat([va, vb]))
    assert _fig(pooled, "rms_deg") == pytest.approx(np.sqrt((30 * 1 + 10 * 16) / 40))
    assert _fig(pooled, "rms_deg") != pytest.approx((1.0 + 4.0) / 2)


def test_bins_are_also_given_per_joint_group():
    a, fa = _ramp_case(1.0)  # left leg, 30 values off by 1
    T = 20
    truth = np.zeros((T, 2))
    obs = np.ones((T, 2), bool)
    obs[5:15, 1] = False  # 10 values of the head off by 4, a 0.1 s gap
    b = _case(truth, obs, ["lfemur.rx", "head.rx"])
    fb = np.where(obs, truth, 4.0)
    s = metrics.summarise(metrics.Values.concat([metrics.values(a, fa, None, GAP_GROUPS),
                                                  metrics.values(b, fb, None, GAP_GROUPS)]))
    assert _fig(s, "rms_deg[group head-neck, len 0.1-0.25s]") == pytest.approx(4.0)
    assert _fig(s, "rms_deg[group left-leg, len 0.25-0.5s]") == pytest.approx(1.0)
    assert _fig(s, "rms_deg[group head-neck, since first]") == pytest.approx(4.0)
    assert not [m for m, _, _ in s if m.startswith("rms_deg[group head-neck, len 0.25")]
    assert "rms_deg[group left-leg, len 0.1-0.25s]" not in [m for m, _, _ in s]


def test_steps_inside_gaps_pop_is_what_the_fill_jumps_beyond_the_truth():
    case, _ = _ramp_case(0.0)   # truth rises 1 degree a frame; erased frames 10-39
    # a fill that follows the truth but steps up by 5 degrees at gap frame 12 (frame 22) and stays
    fill = np.where(case.observed, case.truth, case.truth + np.where(np.arange(60)[:, None] >= 22, 5.0, 0.0))
    s = metrics.summarise(metrics.values(case, fill, None, GAP_GROUPS))
    # 29 values after the first frame; one of them moved 6 where the truth moved 1: a pop of 5
    assert _fig(s, "pop_max_deg") == pytest.approx(5.0)
    assert _fig(s, "pop_over_2deg") == pytest.approx(1 / 29)
    assert _fig(s, "step_err_rms_deg") == pytest.approx(np.sqrt(25 / 29))
    assert _fig(s, "truth_step_rms_deg") == pytest.approx(1.0)
    # hold moves less than the truth every frame: no pop at all, a step error of 1 every frame
    hold = np.where(case.observed, case.truth, 9.0)
    h = metrics.summarise(metrics.values(case, hold, None, GAP_GROUPS))
    assert _fig(h, "pop_max_deg") == 0.0 and _fig(h, "pop_over_2deg") == 0.0
    assert _fig(h, "step_err_rms_deg") == pytest.approx(1.0)
    # pooled tables keep the step figures (concat carries the new fields)
    p = metrics.summarise(metrics.Values.concat([metrics.values(case, fill, None, GAP_GROUPS),
                                                  metrics.values(case, hold, None, GAP_GROUPS)]))
    assert _fig(p, "pop_over_2deg") == pytest.approx(1 / 58)
