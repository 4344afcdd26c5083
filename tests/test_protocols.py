"""The fill protocols reproduce the papers' nearest-neighbour figures, and every baseline runs
on every protocol (issue 2)."""
import json
import subprocess
import sys

import numpy as np
import pytest

from mocap.evaluate import evaluate
from mocap.protocols import get_protocol


def _value(res, test, erased, metric):
    (v,) = [r["value"] for r in res["results"] if r["test"] == test and r["erased"] == erased and r["metric"] == metric]
    return v


def test_pan2009_nearest_neighbour_reproduces_15_8(data):
    res = evaluate("pan2009", "nn", progress=False)
    assert _value(res, "07_01", "all-but-legs", "mse_deg2") == pytest.approx(15.8, rel=0.15)


@pytest.mark.parametrize("method,leg,body", [("nn", 16.2, 23.3), ("scaled-nn", 12.5, 29.9)])
def test_taylor2007_nearest_neighbour_reproduces_published_rerun(data, method, leg, body):
    res = evaluate("taylor2007", method, progress=False)
    assert _value(res, "35_29", "right-leg", "cumulative_scaled_error") == pytest.approx(leg, rel=0.15)
    assert _value(res, "35_29", "upper-body", "cumulative_scaled_error") == pytest.approx(body, rel=0.15)


def test_pan2009_erases_all_but_the_14_leg_channels_over_the_second_half(data):
    (case,) = get_protocol("pan2009").cases()
    T = case.truth.shape[0]
    assert case.observed[: T // 2].all()
    missing = ~case.observed[T // 2 :]
    assert (missing.all(0) | ~missing.any(0)).all()  # the same channels on every erased frame
    assert (~missing.any(0)).sum() == 14
    assert case.scored.sum() == 48 - 3  # upper body and root rotation; translation scored apart


def test_taylor2007_patterns_are_7_and_36_channels(data):
    cases = get_protocol("taylor2007").cases()
    assert {(c.test, c.erased) for c in cases} == {(t, e) for t in ("35_18", "35_29") for e in ("right-leg", "upper-body")}
    for c in cases:
        assert c.scored.sum() == {"right-leg": 7, "upper-body": 36}[c.erased]
        assert c.truth.shape[0] == {"35_18": 44, "35_29": 125}[c.test]
        assert (~c.observed).any(1).argmax() == c.truth.shape[0] // 2


def test_taylor2007_training_split_is_31_sequences_at_30hz(data):
    ts = get_protocol("taylor2007").training_set()
    assert len(ts.sequences) == 31 and ts.n_frames == 2644 and ts.fps == 30.0


def test_gaps_is_seeded_and_looks_like_a_take(data):
    a = get_protocol("gaps", seed=3).cases()
    b = get_protocol("gaps", seed=3).cases()
    c = get_protocol("gaps", seed=4).cases()
    assert all(np.array_equal(x.observed, y.observed) for x, y in zip(a, b))
    assert any(not np.array_equal(x.observed, y.observed) for x, y in zip(a, c))
    for case in a:
        bursts = case.info["bursts"]
        assert bursts, case.test
        for _g, s, e in bursts:
            assert (e - s) / case.fps <= 2.0 + 1e-9
        # several groups out at once somewhere in the takes
    overlap = max(int(((~x.observed).reshape(x.observed.shape).sum(1) > 0).sum()) for x in a)
    assert overlap > 0
    simultaneous = max(len({g for g, s, e in x.info["bursts"] if s <= t < e}) for x in a for t in range(x.truth.shape[0]))
    assert simultaneous >= 2


@pytest.mark.parametrize("protocol", ["pan2009", "taylor2007", "gaps"])
@pytest.mark.parametrize("method", ["hold", "nn", "scaled-nn", "interp"])
def test_every_baseline_runs_on_every_protocol(data, protocol, method):
    res = evaluate(protocol, method, progress=False)
    vals = [r["value"] for r in res["results"] if r["value"] is not None]
    assert vals and all(np.isfinite(vals))
    # only calibration may be n/a, and only for a method that reports no std (nn's is zero)
    na = {r["metric"] for r in res["results"] if r["value"] is None}
    assert na <= {"within_1std", "within_2std", "nll_per_value", "onset_err_over_step"}
    assert bool(na & {"within_2std"}) == method.endswith("nn")
    # an erased channel is filled: the fill differs from NaN and observed entries are untouched
    for case, fill in zip(res["_cases"], res["_fills"]):
        assert np.isfinite(fill).all()
        assert np.array_equal(fill[case.observed], case.truth[case.observed])


def test_interp_beats_hold_on_short_gaps_and_nn_beats_hold_on_pan2009(data):
    gi = evaluate("gaps", "interp", progress=False)
    gh = evaluate("gaps", "hold", progress=False)
    for test in ("07_10", "walking_20"):  # short gaps: the straight line is close; long ones it is not
        assert _value(gi, test, "gaps", "rms_deg[len 0.1-0.25s]") < _value(gh, test, "gaps", "rms_deg[len 0.1-0.25s]")
    assert _value(evaluate("pan2009", "nn", progress=False), "07_01", "all-but-legs", "mse_deg2") < \
        _value(evaluate("pan2009", "hold", progress=False), "07_01", "all-but-legs", "mse_deg2")


def test_lacuna_eval_cli_writes_table_json_and_plot(data, tmp_path):
    out, png = tmp_path / "r.json", tmp_path / "r.png"
    p = subprocess.run([sys.executable, "-m", "lacuna.cli", "eval", "--protocol", "taylor2007", "--method", "scaled-nn",
                        "--json", str(out), "--plot", str(png)], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert "cumulative_scaled_error" in p.stdout
    doc = json.loads(out.read_text())
    assert doc["protocol"] == "taylor2007" and doc["method"] == "scaled-nn"
    assert {"test", "erased", "metric", "value"} <= set(doc["results"][0])
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


def test_eval_scores_another_recording_with_test_file(data, tmp_path):
    from mocap.datasets import trial_path

    res = evaluate("pan2009", "nn", test_file=str(trial_path("02_01")), progress=False)
    assert {r["test"] for r in res["results"]} == {"02_01", "all"}  # the take and its pooled rows
    res = evaluate("taylor2007", "nn", test_file=str(trial_path("35_29")), progress=False)
    # the 120 Hz file resampled to 30 Hz is the protocol's own 35_29 test
    assert _value(res, "35_29", "right-leg", "cumulative_scaled_error") == pytest.approx(16.2, rel=0.15)


def test_eval_cli_unknown_method_is_one_clear_line():
    p = subprocess.run([sys.executable, "-m", "lacuna.cli", "eval", "--protocol", "pan2009", "--method", "nope"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    assert "unknown method 'nope'" in p.stderr and "Traceback" not in p.stderr
