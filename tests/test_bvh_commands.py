"""Issue 20: the commands that take motion files work on BVH of every shipped naming, and a model
trained on CMU's BVH fills a BVH take through a real daemon process (``lacuna replay --serve``
starts one: clients/harness.py)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from skeleton_headers import NAMINGS, bvh_text

from clients.takes import drop_mask
from lacuna.cli import main
from mocap.io import read_motion
from mocap.representation import is_angle, wrap180
from mocap.tpose import skip_tpose

TINY_HLM = ["--styles", "1", "--restarts", "1", "--iterations", "3", "-N", "120", "-q"]


def _hold_rms(truth: np.ndarray, observed: np.ndarray, channels: list[str]) -> float:
    """RMS of holding each channel's last observed value over the erased angle values."""
    held = truth.copy()
    for t in range(1, truth.shape[0]):
        held[t] = np.where(observed[t], truth[t], held[t - 1])
    ang = np.array([is_angle(c) for c in channels])
    m = ~observed & ang[None]
    return float(np.sqrt(np.mean(wrap180(held - truth)[m] ** 2)))


@pytest.mark.realdata
def test_model_trained_on_cmu_bvh_fills_a_bvh_take_through_the_daemon(data, tmp_path, capsys):
    model = tmp_path / "bvh_hlm.npz"
    assert main(["train", "hlm", str(data / "bvh" / "08_02.bvh"), "-o", str(model), *TINY_HLM]) == 0
    take = data / "bvh" / "07_01.bvh"
    out, js = tmp_path / "07_01.filled.bvh", tmp_path / "replay.json"
    assert main(["replay", str(take), "--serve", str(model), "--drop", "gaps", "--speed", "0", "--out", str(out),
                 "--json", str(js), "-q"]) == 0
    r = json.loads(js.read_text())
    truth = skip_tpose(read_motion(take), quiet=True)
    observed, _ = drop_mask("gaps", truth, 0)
    acc = r["accuracy"]
    assert acc["erased_angle_values"] == int((~observed).sum()) > 1000
    # a sensible fill: better than holding the last observed value, and joints within centimetres
    assert acc["rms_deg"] < 0.8 * _hold_rms(truth.frames, observed, truth.channels)
    jp = r["joint_positions"]
    assert jp["n"] > 1000 and 0.5 < jp["mean_cm"] < 15.0
    back = read_motion(out)
    assert back.channels == truth.channels and back.n_frames == truth.n_frames
    np.testing.assert_allclose(back.frames[observed], truth.frames[observed], atol=0, rtol=0)
    assert "RMS error on" in capsys.readouterr().out


@pytest.mark.parametrize("naming", sorted(NAMINGS))
def test_train_replay_eval_on_each_naming(naming, tmp_path, capsys):
    take = tmp_path / f"{naming}_walk.bvh"
    take.write_text(bvh_text(NAMINGS[naming](), 960))
    model = tmp_path / "m.npz"
    assert main(["train", "hlm", str(take), "-o", str(model), *TINY_HLM]) == 0
    js = tmp_path / "r.json"
    assert main(["replay", str(take), "--serve", str(model), "--drop", "gaps", "--speed", "0",
                 "--out", str(tmp_path / "f.bvh"), "--json", str(js), "-q"]) == 0
    r = json.loads(js.read_text())
    assert r["accuracy"]["erased_angle_values"] > 0 and np.isfinite(r["accuracy"]["rms_deg"])
    assert r["joint_positions"]["n"] > 0
    ej = tmp_path / "e.json"
    assert main(["eval", "--protocol", "gaps", "--method", "hlm", "--model", str(model), "--test", str(take),
                 "--json", str(ej), "-q"]) == 0
    rows = {x["metric"]: x["value"] for x in json.loads(ej.read_text())["results"] if x["test"] == take.stem}
    assert np.isfinite(rows["rms_deg"]) and np.isfinite(rows["joint_pos_mean_cm"])
    capsys.readouterr()


def test_crbm_with_a_heading_relative_root_on_a_mixamo_take(tmp_path, capsys):
    """CRBM's heading-relative root (``--root-mode relative``; the faithful default is the raw root):
    on a Mixamo take (Zrotation Xrotation Yrotation, ``mixamorig:`` names) it goes through mocap.rootframe."""
    take = tmp_path / "mixamo.bvh"
    take.write_text(bvh_text(NAMINGS["humanik"](), 480))
    model = tmp_path / "c.npz"
    assert main(["train", "crbm", str(take), "-o", str(model), "--epochs", "5", "--hidden", "20", "--fps", "120",
                 "--root-mode", "relative", "-q"]) == 0
    from crbm.persist import load

    rep = load(str(model)).representation
    assert rep.root == {"rot": ["mixamorig:Hips.rx", "mixamorig:Hips.ry", "mixamorig:Hips.rz"], "order": "zxy",
                        "pos": ["mixamorig:Hips.tx", "mixamorig:Hips.ty", "mixamorig:Hips.tz"], "up": "y"}
    js = tmp_path / "r.json"
    assert main(["replay", str(take), "--serve", str(model), "--drop", "gaps:root,left-leg", "--speed", "0",
                 "--out", str(tmp_path / "f.bvh"), "--json", str(js), "-q"]) == 0
    r = json.loads(js.read_text())
    assert r["accuracy"]["erased_values"] > 0 and r["joint_positions"]["n"] > 0
    gen = tmp_path / "gen.bvh"
    assert main(["generate", "crbm", str(model), "--seed-frames", str(take), "--frames", "20", "-o", str(gen)]) == 0
    g = read_motion(gen)
    assert g.channels == read_motion(take).channels and g.n_frames == 4 + 20 and np.isfinite(g.frames).all()
    capsys.readouterr()


def test_a_drop_with_nothing_to_erase_is_an_error_not_a_zero_report(tmp_path, capsys):
    """The issue's report: a drop pattern that erased nothing said 'RMS error on 0 erased angle
    values' and exited 0.  Now it fails before any daemon starts, naming the skeleton."""
    take = tmp_path / "mixamo.bvh"
    take.write_text(bvh_text(NAMINGS["humanik"](), 240))
    # read as OptiTrack's naming, its left arm (LShoulder, LUArm, LFArm, LHand) is not in the take
    assert main(["replay", str(take), "--serve", str(tmp_path / "absent.npz"), "--drop", "gaps:left-arm",
                 "--skeleton", "optitrack-motive", "-q"]) == 2
    err = capsys.readouterr().err
    assert "lacuna: error: --drop gaps:left-arm: " in err
    assert "(skeleton optitrack-motive) has no channels in left-arm: looked for bones LFArm" in err
    assert main(["replay", str(take), "--serve", str(tmp_path / "absent.npz"), "--skeleton", "nope", "-q"]) == 2


@pytest.mark.realdata
def test_replay_positions_csv_is_forward_kinematics(data, tmp_path):
    from mocap.csvio import read_csv
    from mocap.fk import Kinematics

    model = tmp_path / "m.npz"
    assert main(["train", "hlm", str(data / "bvh" / "08_02.bvh"), "-o", str(model), *TINY_HLM]) == 0
    csv = tmp_path / "pos.csv"
    take = data / "bvh" / "09_11.bvh"
    assert main(["replay", str(take), "--serve", str(model), "--drop", "gaps", "--speed", "0", "--out", str(csv),
                 "--positions", "-q"]) == 0
    truth = skip_tpose(read_motion(take), quiet=True)
    kin = Kinematics.from_motion(truth)
    P = read_csv(str(csv))
    assert P.channels[:3] == ["Hips.x", "Hips.y", "Hips.z"] and len(P.channels) == 3 * len(kin.joints)
    assert P.n_frames == truth.n_frames and np.isfinite(P.frames).all()
    # frames with nothing erased come back as sent: their positions are the truth's FK (metres)
    observed, _ = drop_mask("gaps", truth, 0)
    whole = observed.all(1)
    assert whole.sum() > 10 and not whole.all()
    np.testing.assert_allclose(P.frames[whole], kin.positions(truth.frames[whole]).reshape(int(whole.sum()), -1),
                               atol=1e-9, rtol=0)
    # and the Hips stand about a metre above CMU's floor (z up, 1/0.45-inch units)
    assert 0.7 < np.median(P.frames[:, 2]) < 1.2


@pytest.mark.realdata
def test_eval_trains_on_bvh_files_and_scores_bvh_takes_with_a_protocol(data, tmp_path, capsys):
    """The gaps protocol on CMU's BVH: hold and nn trained on 08_02.bvh, scored on 07_01.bvh."""
    out = {}
    for method in ("hold", "nn"):
        js = tmp_path / f"{method}.json"
        assert main(["eval", "--protocol", "gaps", "--method", method, "--train", str(data / "bvh" / "08_02.bvh"),
                     "--test", str(data / "bvh" / "07_01.bvh"), "--json", str(js), "-q"]) == 0
        res = json.loads(js.read_text())
        assert res["trained_on"] == ["08_02"]
        out[method] = {r["metric"]: r for r in res["results"] if r["test"] == "07_01"}
    for method, rows in out.items():
        assert rows["rms_deg"]["n"] > 1000 and 0 < rows["joint_pos_mean_cm"]["value"] < 30, method
        assert rows["rms_deg[group left-arm]"]["n"] > 0 and rows["rms_deg[group torso]"]["n"] > 0
    # the same erasure for both: the same values scored
    assert out["hold"]["rms_deg"]["n"] == out["nn"]["rms_deg"]["n"]
    capsys.readouterr()


def test_a_model_trained_from_files_carries_its_skeleton_for_fk(tmp_path, capsys):
    from lacuna.modelfile import load_model
    from mocap.fk import Kinematics, from_record

    take = tmp_path / "vicon.bvh"
    take.write_text(bvh_text(NAMINGS["vicon-shogun"](), 480))
    m = read_motion(take)
    for cmd in (["train", "hlm", str(take), "-o", str(tmp_path / "h.npz"), *TINY_HLM],
                ["train", "crbm", str(take), "-o", str(tmp_path / "c.npz"), "--epochs", "3", "--hidden", "10",
                 "--fps", "120", "-q"]):
        assert main(cmd) == 0
        model = load_model(cmd[cmd.index("-o") + 1])
        kin = from_record(model.meta["training"]["skeleton"], model.channels)
        want = Kinematics.from_motion(m)
        assert kin.joints == want.joints and kin.length_unit == want.length_unit
        np.testing.assert_allclose(kin.positions(m.frames[:5]), want.positions(m.frames[:5]), atol=1e-12)
    capsys.readouterr()


def test_positions_need_a_csv_output_and_fail_before_any_daemon(tmp_path, capsys):
    take = tmp_path / "x.bvh"
    take.write_text(bvh_text(NAMINGS["xsens-mvn"](), 120))
    assert main(["replay", str(take), "--serve", str(tmp_path / "absent.npz"), "--out", str(tmp_path / "y.bvh"),
                 "--positions", "-q"]) == 2
    assert "--positions writes joint positions as CSV" in capsys.readouterr().err
