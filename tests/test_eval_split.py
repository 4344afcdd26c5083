"""`lacuna eval` on the train / validation / test split (issue 17): the split loads, the gaps
protocol trains on TRAIN and scores VALIDATION or TEST, seeds and activities pool values, one
model scores repeated --test files, --fills writes what the figures come from, and pan2009 can
score the validation walk 07_10 with a model that never saw it.  hold, interp and nn train in
about a second, so these run on the real takes."""
import json
import subprocess
import sys

import numpy as np
import pytest

from mocap import splits
from mocap.evaluate import evaluate, value
from mocap.protocols import Gaps, load_take
from mocap.representation import is_angle, wrap180

pytestmark = pytest.mark.realdata


def _lacuna(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "lacuna.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


def _amc(data, take):
    return data / "cmu" / take.split("_")[0] / f"{take}.amc" if take[0].isdigit() else data / "cmu_li" / f"{take}.amc"


def test_split_is_disjoint_labelled_and_loads(data):
    tr, va, te = map(set, (splits.TRAIN, splits.VALIDATION, splits.TEST))
    assert not (tr & va or tr & te or va & te)
    assert not set(splits.PAPER_TESTS) & (tr | va | te)
    for take in tr | va | te:
        assert splits.ACTIVITY[take] in ("walk", "turn", "run", "nonloco"), take
    # every activity is on both sides of the split it is scored on
    for acts in ({splits.ACTIVITY[t] for t in va}, {splits.ACTIVITY[t] for t in te}):
        assert acts == {"walk", "turn", "run", "nonloco"}
    for take in sorted(va | te):
        m = load_take(take)
        assert m.fps == 120.0 and len(m.channels) == 62 and m.n_frames > 100, take
        assert splits.split_of(take) in ("validation", "test")
    assert splits.split_of("07_01") == "paper-test" and splits.split_of("nope") is None


def test_gaps_trains_on_train_and_scores_validation_by_default(data):
    g = Gaps()
    assert g.training_set().names == splits.TRAIN
    assert {splits.ACTIVITY[t] for t in g.training_set().names} >= {"walk", "nonloco"}
    assert [c.test for c in g.cases()] == splits.VALIDATION
    assert [c.test for c in Gaps(split="test").cases()] == splits.TEST
    with pytest.raises(ValueError, match="validation or test"):
        Gaps(split="train")
    # the root is a group of its own: some burst erases root.tx on some take
    assert any(g == "root" for c in g.cases() for g, _, _ in c.info["bursts"])


def test_seeds_and_activities_pool_the_erased_values(data):
    res = evaluate("gaps", "hold", seeds=[0, 1], progress=False)
    assert res["seeds"] == [0, 1] and res["split"] == "validation"
    assert len(res["_cases"]) == 2 * len(splits.VALIDATION)

    def pooled(select):
        errs = [wrap180(f - c.truth)[c.missing & (c.scored & np.array([is_angle(n) for n in c.channels]))[None]]
                for c, f in zip(res["_cases"], res["_fills"]) if select(c)]
        return float(np.sqrt(np.mean(np.concatenate(errs) ** 2)))

    for act in ("walk", "turn", "run", "nonloco"):
        want = pooled(lambda c: splits.ACTIVITY[c.test] == act)
        assert value(res, "rms_deg", activity=act) == pytest.approx(want)
    assert value(res, "rms_deg") == pytest.approx(pooled(lambda c: True))
    # a take's row pools both seeds: it differs from either seed alone
    one = evaluate("gaps", "hold", seeds=[0], progress=False)
    both, first = value(res, "rms_deg", test="walking_20"), value(one, "rms_deg", test="walking_20")
    assert both == pytest.approx(pooled(lambda c: c.test == "walking_20"))
    assert both != pytest.approx(first)
    rows = [r for r in res["results"] if r["test"] == "walking_20"]
    assert {r["split"] for r in rows} == {"validation"} and {r["activity"] for r in rows} == {"walk"}
    assert not any(r["in_training"] for r in rows)


def test_test_split_rows_say_test(data):
    res = evaluate("gaps", "interp", split="test", progress=False)
    per_take = [r for r in res["results"] if r["test"] != "all"]
    assert {r["test"] for r in per_take} == set(splits.TEST)
    assert {r["split"] for r in res["results"]} == {"test"}
    from mocap.evalreport import format_table

    assert "TEST figures" in format_table(res).splitlines()[0]


def test_repeated_test_files_and_fills_npz_hold_what_the_figures_come_from(data, tmp_path):
    a, b = _amc(data, "walking_21"), _amc(data, "49_19")
    out = tmp_path / "r.json"
    p = _lacuna("eval", "--protocol", "gaps", "--method", "interp", "--test", a, "--test", b,
                "--fills", tmp_path / "fills", "--json", out, "--seed", 2)
    assert p.returncode == 0, p.stderr
    assert p.stderr.count("training interp") == 1  # one model for both files
    doc = json.loads(out.read_text())
    assert {r["test"] for r in doc["results"]} == {"walking_21", "49_19", "all"}
    assert {r["activity"] for r in doc["results"] if r["test"] != "all"} == {"walk", "nonloco"}
    assert sorted(f.name for f in (tmp_path / "fills").iterdir()) == ["49_19.npz", "walking_21.npz"]
    z = np.load(tmp_path / "fills" / "walking_21.npz")
    assert {"truth", "fill", "std", "erased", "channels", "fps"} <= set(z.files)
    m = load_take("walking_21")
    assert np.array_equal(z["truth"], m.frames) and list(z["channels"]) == m.channels and float(z["fps"]) == 120.0
    obs, _ = Gaps(seed=2).occlusion("walking_21", m.n_frames, m.channels, m.fps)
    assert np.array_equal(z["erased"], ~obs)
    assert np.array_equal(z["fill"][obs], m.frames[obs])
    assert z["std"].shape == m.frames.shape and (z["std"][z["erased"]] > 0).all()  # interp reports the training std
    # the JSON's figure is what the npz gives
    ang = np.array([is_angle(c) for c in m.channels])
    e = wrap180(z["fill"] - z["truth"])[z["erased"] & ang[None]]
    (row,) = [r for r in doc["results"] if r["test"] == "walking_21" and r["metric"] == "rms_deg"]
    assert row["value"] == pytest.approx(np.sqrt(np.mean(e**2)))


def test_fills_name_the_pattern_and_the_seed_where_there_are_several(data, tmp_path):
    p = _lacuna("eval", "--protocol", "taylor2007", "--method", "nn", "--fills", tmp_path / "t", "-q")
    assert p.returncode == 0, p.stderr
    assert sorted(f.name for f in (tmp_path / "t").iterdir()) == [
        "35_18-right-leg.npz", "35_18-upper-body.npz", "35_29-right-leg.npz", "35_29-upper-body.npz"]
    z = np.load(tmp_path / "t" / "35_29-right-leg.npz")
    assert z["erased"].any(0).sum() == 7 and float(z["fps"]) == 30.0
    p = _lacuna("eval", "--protocol", "gaps", "--method", "hold", "--test", _amc(data, "soccer_4"), "--seeds", "0-1",
                "--fills", tmp_path / "g", "-q")
    assert p.returncode == 0, p.stderr
    assert sorted(f.name for f in (tmp_path / "g").iterdir()) == ["soccer_4-seed0.npz", "soccer_4-seed1.npz"]


def test_pan2009_scores_the_validation_walk_with_a_model_that_never_saw_it(data):
    res = evaluate("pan2009", "nn", split="validation", progress=False)
    assert "07_10" not in res["trained_on"]
    assert not set(res["trained_on"]) & set(splits.VALIDATION + splits.TEST + splits.PAPER_TESTS)
    tests = {r["test"] for r in res["results"]} - {"all"}
    assert "07_10" in tests and tests <= set(splits.VALIDATION)
    assert not any(r.get("in_training") for r in res["results"])
    nn_mse = value(res, "mse_deg2", test="07_10")
    # the paper's training set holds 07_10: the same file scored then is flagged, and near perfect
    seen = evaluate("pan2009", "nn", test_file=str(_amc(data, "07_10")), progress=False)
    assert all(r["in_training"] for r in seen["results"] if r["test"] == "07_10")
    assert value(seen, "mse_deg2", test="07_10") < 0.01 * nn_mse
    held = evaluate("pan2009", "nn", test_file=str(_amc(data, "07_10")), train_split=True, progress=False)
    assert value(held, "mse_deg2", test="07_10") == pytest.approx(nn_mse)
    # the root is erased over the second half: its error is in cm, beside hold's
    assert value(res, "root_pos_rms_cm", test="07_10") > 0 and value(res, "hold_root_pos_rms_cm", test="07_10") > 0


def test_nn_reports_no_std_so_its_calibration_is_na_and_plot_has_the_band(data, tmp_path):
    p = _lacuna("eval", "--protocol", "pan2009", "--method", "nn", "--split", "validation", "--plot", tmp_path / "p.png",
                "--json", tmp_path / "p.json")
    assert p.returncode == 0, p.stderr
    assert "within_2std" in p.stdout and "n/a" in p.stdout
    doc = json.loads((tmp_path / "p.json").read_text())
    assert all(r["value"] is None for r in doc["results"] if r["metric"] == "within_2std")
    assert (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("args,msg", [
    (["--protocol", "gaps", "--method", "hold", "--seeds", "x-2"], "--seeds expects"),
    (["--protocol", "taylor2007", "--method", "hold", "--split", "validation"], "own training and test split"),
    (["--protocol", "pan2009", "--method", "hold", "--seeds", "0-2"], "seeds apply to the gaps protocol only"),
    (["--protocol", "gaps", "--method", "hold", "--test", "/nonexistent/x.amc"], "x.amc"),
])
def test_eval_bad_arguments_are_one_clear_line(data, args, msg):
    p = _lacuna("eval", *args)
    assert p.returncode == 2
    assert msg in p.stderr and "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1
