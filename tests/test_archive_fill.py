"""lacuna fill in this process (--workers 0): real gaps in every format, sidecars, resume, bad takes.
The Dask cluster runs are in test_archive_cluster.py."""
from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest

from archive.formats import FILL_SUFFIX, MASK_SUFFIX, runs_decode, std_decode, write_mask
from lacuna.cli import main

pytestmark = pytest.mark.realdata


def _take(data, rel):
    return os.path.join(data, rel)


def _copy_amc(data, tmp_path, take="07_02"):
    d = tmp_path / "in"
    d.mkdir(exist_ok=True)
    subj = take.split("_")[0]
    shutil.copy(_take(data, f"cmu/{subj}/{take}.amc"), d / f"{take}.amc")
    shutil.copy(_take(data, f"cmu/{subj}/{subj}.asf"), d / f"{subj}.asf")
    return d / f"{take}.amc"


def test_csv_with_nan_gaps_is_filled_by_interpolation(data, tmp_path):
    from mocap.asf import read_amc
    from mocap.baselines import InterpModel
    from mocap.csvio import read_csv, write_csv
    from mocap.motion import Motion

    m = read_amc(_take(data, "cmu/07/07_02.amc"))
    frames = m.frames.copy()
    arm = [j for j, c in enumerate(m.channels) if c.startswith(("rhumerus", "rradius"))]
    frames[100:160, arm] = np.nan                       # a 0.5 s dropout of the right arm
    frames[200:203, 0] = np.nan                         # and a short one of root.tx
    src = tmp_path / "take.csv"
    write_csv(src, Motion(frames, m.channels, m.fps, None, "07_02"))
    out = tmp_path / "out"
    assert main(["fill", str(src), "--out", str(out), "--method", "interp", "--workers", "0", "-q"]) == 0
    got = read_csv(out / "take.csv")
    assert np.all(np.isfinite(got.frames))
    known = np.isfinite(frames)
    assert np.array_equal(got.frames[known], frames[known])          # captured values untouched, exactly
    ref, ref_std = InterpModel(m.channels, np.zeros(len(m.channels)), np.ones(len(m.channels))).fill_offline(
        np.nan_to_num(frames), known)
    np.testing.assert_allclose(got.frames[~known], ref[~known], atol=1e-9)
    side = json.loads((out / ("take.csv" + FILL_SUFFIX)).read_text())
    assert side["method"] == "interp" and side["causal"] is False and side["model"] is None
    assert side["values_filled"] == int((~known).sum()) == side["real_gap_values"]
    assert np.array_equal(runs_decode(side["filled"], side["channels"], side["frames"]), ~known)
    assert side["filled"]["root.tx"] == [[200, 203]]
    std = std_decode(side, side["channels"])
    assert np.all(std[~known] > 0) and np.all(std[known] == 0)


def test_amc_mask_sidecar_marks_the_real_gaps(data, tmp_path):
    from mocap.asf import read_amc

    src = _copy_amc(data, tmp_path)
    m = read_amc(src)
    missing = np.zeros(m.frames.shape, bool)
    missing[50:90, m.index(["lfemur.rx", "lfemur.ry"])] = True
    write_mask(str(src) + MASK_SUFFIX, missing, m.channels)
    out = tmp_path / "out"
    assert main(["fill", str(tmp_path / "in"), "--out", str(out), "--method", "hold", "--workers", "0", "-q"]) == 0
    got = read_amc(out / "07_02.amc")                    # the ASF was written beside it
    side = json.loads((out / ("07_02.amc" + FILL_SUFFIX)).read_text())
    assert side["filled"] == {"lfemur.rx": [[50, 90]], "lfemur.ry": [[50, 90]]}
    j = m.index(["lfemur.rx"])[0]
    # hold: every filled value is the last captured one (AMC text keeps 6 decimals)
    np.testing.assert_allclose(got.frames[50:90, j], m.frames[49, j], atol=1e-5)
    np.testing.assert_allclose(got.frames[~missing], m.frames[~missing], atol=1e-5)


def test_recording_keeps_its_mask_and_gains_fills(data, tmp_path):
    from clients.recording import read_recording, write_motion_recording
    from mocap.asf import read_amc

    m = read_amc(_take(data, "cmu/35/35_01.amc"))
    obs = np.ones(m.frames.shape, bool)
    obs[30:80, 20:30] = False
    src = tmp_path / "take.lrec"
    write_motion_recording(src, m, obs)
    out = tmp_path / "out"
    assert main(["fill", str(src), "--out", str(out), "--method", "interp", "--workers", "0", "-q"]) == 0
    rec = read_recording(out / "take.lrec")
    assert np.array_equal(rec.observed, obs)                          # raw frames and mask as they were
    assert np.array_equal(rec.filled, ~obs)
    done = rec.to_motion().frames
    assert np.all(np.isfinite(done))
    np.testing.assert_allclose(done[obs], m.frames[obs].astype(np.float32), rtol=1e-6)
    assert np.all(rec.std[~obs] > 0)


def test_bad_take_is_reported_and_the_batch_goes_on(data, tmp_path, capsys):
    d = tmp_path / "in"
    d.mkdir()
    (d / "broken.amc").write_text("this is not an AMC file\n")
    shutil.copy(_take(data, "cmu/07/07.asf"), d / "07.asf")
    shutil.copy(_take(data, "cmu/07/07_02.amc"), d / "07_02.amc")
    (d / "empty.csv").write_text("")
    out, js = tmp_path / "out", tmp_path / "summary.json"
    rc = main(["fill", str(d), "--out", str(out), "--method", "hold", "--workers", "0", "-q", "--json", str(js)])
    assert rc == 1
    s = json.loads(js.read_text())["summary"]
    assert (s["takes"], s["filled"], s["failed"]) == (3, 1, 2)
    assert sorted(os.path.basename(f["source"]) for f in s["failures"]) == ["broken.amc", "empty.csv"]
    assert (out / "07_02.amc").exists() and not (out / "broken.amc").exists()
    assert "FAILED" in capsys.readouterr().out


def test_resume_skips_done_takes_and_redoes_a_newer_input(data, tmp_path):
    src = _copy_amc(data, tmp_path, "07_02")
    shutil.copy(_take(data, "cmu/07/07_09.amc"), tmp_path / "in" / "07_09.amc")
    out, js = tmp_path / "out", tmp_path / "s.json"
    args = [str(tmp_path / "in"), "--out", str(out), "--method", "interp", "--workers", "0", "-q", "--json", str(js)]
    assert main(["fill", *args]) == 0
    t09 = os.path.getmtime(out / "07_09.amc")
    assert main(["fill", *args]) == 0
    assert json.loads(js.read_text())["summary"]["skipped"] == 2
    st = os.stat(out / "07_02.amc")
    os.utime(src, (st.st_mtime + 5, st.st_mtime + 5))                 # the input changed after its output
    assert main(["fill", *args]) == 0
    s = json.loads(js.read_text())
    assert [os.path.basename(r["source"]) for r in s["takes"]] == ["07_02.amc"]
    assert os.path.getmtime(out / "07_09.amc") == t09
    # another method is not "done"
    assert main(["fill", *args[:4], "hold", *args[5:]]) == 0
    assert json.loads(js.read_text())["summary"]["filled"] == 2


@pytest.mark.parametrize("argv, msg", [
    (["--method", "hlm"], "needs a trained model"),
    (["--method", "nosuch"], "unknown method"),
    ([], "give --model FILE"),
    (["--method", "hold", "--drop", "nosuch"], "unknown pattern"),
    (["--model", "/nonexistent.npz"], "no such file"),
])
def test_bad_command_lines_are_one_line_errors(data, tmp_path, capsys, argv, msg):
    rc = main(["fill", _take(data, "cmu/07/07_02.amc"), "--out", str(tmp_path / "o"), *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("lacuna: error:") and msg in err[0]


def test_unreachable_scheduler_is_a_one_line_error(data, tmp_path, capsys, monkeypatch):
    import socket

    import archive.cluster

    monkeypatch.setattr(archive.cluster, "CONNECT_TIMEOUT_S", 2)
    with socket.socket() as s:          # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    rc = main(["fill", _take(data, "cmu/07/07_02.amc"), "--out", str(tmp_path / "o"), "--method", "hold",
               "--scheduler", f"tcp://127.0.0.1:{port}", "-q"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("lacuna: error: --scheduler") and "cannot connect" in err[0]
    assert not (tmp_path / "o" / "07_02.amc").exists()


def test_outputs_of_several_skeletons_in_one_folder_each_read_with_their_own(data, tmp_path):
    """An output folder holding takes of subject 07, subject 35 and a cmu_li take: each output has
    its own ASF beside it under the name mocap.asf.find_asf tries first, in any order of writing."""
    from mocap.asf import find_asf
    from mocap.io import read_motion

    takes = [os.path.join(data, t) for t in ("cmu/07/07_02.amc", "cmu/35/35_01.amc", "cmu_li/walking_13.amc")]
    out = tmp_path / "out"
    for order in (takes, takes[::-1]):
        assert main(["fill", *order, "--out", str(out), "--method", "hold", "--drop", "gaps", "--force",
                     "--workers", "0", "-q"]) == 0
        assert os.path.basename(find_asf(out / "walking_13.amc")) == "walking_13.asf"
        assert os.path.basename(find_asf(out / "07_02.amc")) == "07.asf"
        assert os.path.basename(find_asf(out / "35_01.amc")) == "35.asf"
        for t in takes:
            got = read_motion(str(out / os.path.basename(t)))
            assert got.channels == read_motion(t).channels
        for f in out.glob("*.asf"):
            f.unlink()
