"""`lacuna replay` and `lacuna record` against a real daemon process, on real CMU takes (issue 6)."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from clients import Client
from clients.configfile import free_port
from clients.harness import DaemonProcess
from clients.record import record
from clients.recording import RecordingWriter, read_recording
from clients.takes import drop_mask
from daemon import wire
from lacuna.cli import main
from lacuna.errors import LacunaError, ParseError
from mocap.asf import find_asf, read_amc
from mocap.baselines import HoldModel
from mocap.datasets import load_trial, trial_path
from mocap.motion import Motion


@pytest.fixture(scope="module")
def daemon(tmp_path_factory, data):
    m = load_trial("07_02")
    d = tmp_path_factory.mktemp("replay")
    HoldModel.fit([m.frames], m.channels).save(str(d / "hold.npz"))
    proc = DaemonProcess({"hold": str(d / "hold.npz")}, workdir=str(d / "daemon"), daemon={"budget_ms": 200.0},
                         zmq={"pub": f"tcp://127.0.0.1:{free_port()}"})
    proc.start()
    yield proc
    proc.stop()


def test_replay_output_equals_input_where_nothing_was_dropped(daemon, tmp_path, capsys):
    src = str(trial_path("07_01"))
    out = tmp_path / "07_01.filled.amc"
    rc = main(["replay", src, "--connect", daemon.endpoint, "--speed", "0", "--drop", "gaps:left-arm,head-neck",
               "--out", str(out), "--json", str(tmp_path / "r.json"), "--plot", str(tmp_path / "r.png"), "-q"])
    assert rc == 0
    truth = read_amc(src)
    got = read_amc(str(out), find_asf(src))
    keep, bursts = drop_mask("gaps:left-arm,head-neck", truth, 0)
    assert bursts and (~keep).any()
    np.testing.assert_array_equal(got.frames[keep], truth.frames[keep])
    # where values were dropped the daemon's hold fill went in, which is not the truth
    assert np.abs(got.frames[~keep] - truth.frames[~keep]).max() > 1.0
    text = capsys.readouterr().out
    assert "RMS error on" in text and (tmp_path / "r.png").stat().st_size > 0


def test_replay_without_drops_writes_the_input_back(daemon, tmp_path):
    src = str(trial_path("07_01"))
    out = tmp_path / "same.amc"
    assert main(["replay", src, "--connect", daemon.endpoint, "--speed", "0", "--out", str(out), "-q"]) == 0
    np.testing.assert_array_equal(read_amc(str(out), find_asf(src)).frames, read_amc(src).frames)


def test_record_then_replay_the_recording(daemon, tmp_path):
    names = load_trial("07_01").channels
    frames = load_trial("07_01").frames[:40]
    path = tmp_path / "take.lrec"
    ready = threading.Event()
    done = threading.Event()
    box: dict = {}
    t = threading.Thread(target=lambda: box.setdefault("n", record(daemon.zmq_opts["pub"], "studio-a", str(path),
                                                                   channels=names, fps=120.0, frames=40, stop=done.is_set,
                                                                   progress=False, ready=ready.set)))
    t.start()
    ready.wait(5)
    # the SUB's subscription reaches the PUB (ZeroMQ slow joiner); generous on a busy machine.  The one
    # sleep left in place of an event: record() reports no first message and a PUB cannot tell who
    # has joined (an XPUB could), and a join frame on this stream would be recorded with the rest
    time.sleep(1.0)
    obs = np.ones(frames.shape, bool)
    obs[10:20, names.index("lhumerus.rx")] = False
    replies = []
    with Client(daemon.endpoint, "studio-a", names, timeout_s=5.0) as c:
        for k in range(40):
            replies.append(c.fill(frames[k], obs[k], t=k / 120.0))
    t.join(30)  # the recorder stops by itself once it has written its 40 frames
    done.set()
    assert box.get("n") == 40
    rec = read_recording(str(path))
    assert rec.channels == names and rec.fps == 120.0
    np.testing.assert_array_equal(rec.observed, obs)
    np.testing.assert_array_equal(rec.raw[obs], frames[obs].astype(np.float32))
    np.testing.assert_array_equal(rec.filled, ~obs)
    np.testing.assert_array_equal(rec.filled_angles, np.array([r.angles for r in replies], np.float64))

    out = tmp_path / "take.filled.lrec"
    assert main(["replay", str(path), "--connect", daemon.endpoint, "--speed", "0", "--out", str(out), "-q"]) == 0
    back = read_recording(str(out))
    np.testing.assert_array_equal(back.raw[obs], rec.raw[obs])
    assert back.filled_angles is not None


def test_recording_reader_errors_and_truncated_tail(tmp_path):
    p = tmp_path / "x.lrec"
    p.write_bytes(b"\x93\x01\x02\x03")
    with pytest.raises(ParseError, match="not a lacuna recording"):
        read_recording(str(p))
    with RecordingWriter(p, ["a", "b"], 30.0) as w:
        for k in range(3):
            w.write(k, k / 30, np.array([k, np.nan]))
    data = p.read_bytes()
    p.write_bytes(data[:-5])  # a recorder killed mid-write
    rec = read_recording(str(p))
    assert rec.seq.tolist() == [0, 1] and rec.observed[:, 1].tolist() == [False, False]
    with pytest.raises(ValueError, match="2 channels"):
        with RecordingWriter(tmp_path / "y.lrec", ["a", "b"]) as w:
            w.write(0, 0.0, np.zeros(3))


def test_drop_patterns():
    m = Motion(np.zeros((600, 3)), ["lhumerus.rx", "head.rx", "lfemur.rx"], 120.0, source="walk.amc")
    obs, bursts = drop_mask("gaps:left-arm", m, 3)
    assert bursts and all(g == "left-arm" for g, _, _ in bursts)
    assert (~obs[:, 0]).any() and obs[:, 1:].all()
    obs, _ = drop_mask("pan2009", m)
    assert obs[:300].all() and not obs[300:, :2].any() and obs[300:, 2].all()
    with pytest.raises(LacunaError, match="unknown joint group 'tail'"):
        drop_mask("gaps:tail", m)
    with pytest.raises(LacunaError, match="unknown pattern"):
        drop_mask("half", m)


def test_replay_refuses_a_missing_file(tmp_path, capsys):
    assert main(["replay", str(tmp_path / "nope.amc"), "--connect", "tcp://127.0.0.1:1", "-q"]) == 2
    assert "nope.amc: no such file" in capsys.readouterr().err


def test_fill_frames_of_a_drop_reply_are_counted_not_invented(daemon):
    # a duplicate seq is answered with a Drop, never with an invented fill
    names = load_trial("07_01").channels
    with Client(daemon.endpoint, "dup", names, timeout_s=5.0) as c:
        f = np.zeros(len(names))
        assert isinstance(c.fill(f, seq=5), wire.FillMsg)
        r = c.fill(f, seq=5)
        assert isinstance(r, wire.Drop) and r.reason == "duplicate"


def test_lacuna_record_process_writes_what_the_daemon_published(daemon, tmp_path):
    import subprocess
    import sys

    names = load_trial("07_01").channels
    frames = load_trial("07_01").frames[:30]
    out = tmp_path / "rec.lrec"
    p = subprocess.Popen([sys.executable, "-m", "lacuna.cli", "record", "--connect", daemon.zmq_opts["pub"],
                          "--stream", "proc-rec", "--out", str(out), "--frames", "20", "--channels", ",".join(names),
                          "--fps", "120", "-q"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # the recorder's SUB joins the PUB some time after it starts (ZeroMQ slow joiner) and
        # misses what was published before: keep streaming until it has its 20 frames
        with Client(daemon.endpoint, "proc-rec", names, timeout_s=5.0) as c:
            k = 0
            while p.poll() is None and k < 3000:
                c.fill(frames[k % len(frames)], t=k / 120.0)
                k += 1
                time.sleep(0.005)  # (pacing: a 200 Hz stream until the recorder, a process, exits)
        so, se = p.communicate(timeout=20)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, se
    assert "recorded 20 frames" in so
    rec = read_recording(str(out))
    assert len(rec.seq) == 20 and rec.channels == names
    assert np.all(np.diff(rec.seq) == 1)
    np.testing.assert_array_equal(rec.raw, frames[rec.seq % len(frames)].astype(np.float32))


def test_replay_csv_take_writes_csv(daemon, tmp_path):
    from mocap import io as mio

    m = load_trial("07_01").slice(0, 120)
    src = tmp_path / "walk.csv"
    mio.write_motion(str(src), m)
    out = tmp_path / "walk.filled.csv"
    assert main(["replay", str(src), "--connect", daemon.endpoint, "--speed", "0", "--drop", "pan2009",
                 "--out", str(out), "-q"]) == 0
    got = mio.read_motion(str(out))
    want = mio.read_motion(str(src))
    keep, _ = drop_mask("pan2009", want)
    assert got.channels == want.channels and got.frames.shape == want.frames.shape
    np.testing.assert_array_equal(got.frames[keep], want.frames[keep])
    assert not np.array_equal(got.frames[~keep], want.frames[~keep])


def test_replay_serve_starts_and_stops_its_own_daemon(tmp_path, data):
    from mocap import io as mio

    m = load_trial("07_01").slice(0, 60)
    HoldModel.fit([load_trial("07_02").frames], m.channels).save(str(tmp_path / "hold.npz"))
    src = tmp_path / "short.csv"
    mio.write_motion(str(src), m)
    out = tmp_path / "short.filled.csv"
    assert main(["replay", str(src), "--serve", str(tmp_path / "hold.npz"), "--speed", "4",
                 "--drop", "taylor2007:right-leg", "--out", str(out), "--json", str(tmp_path / "s.json"), "-q"]) == 0
    import json

    rep = json.loads((tmp_path / "s.json").read_text())
    assert rep["model"] == "model" and sum(rep["status"].values()) == 60 and set(rep["status"]) <= {"ok", "degraded"}
    assert rep["accuracy"]["erased_angle_values"] == 30 * 7
    assert mio.read_motion(str(out)).frames.shape == (60, 62)


def test_replay_reports_the_fill_figures_and_plots_the_band(daemon, tmp_path, capsys):
    """`lacuna replay --json` carries the figures `lacuna eval` and the demo give (mocap.metrics), over
    the dropped values; the hold model's std is its training std, so its band is reported too."""
    import json

    from clients.demo_score import make_case, score
    from mocap.metrics import cm_per_unit

    src = str(trial_path("07_01"))
    out = tmp_path / "f.amc"
    assert main(["replay", src, "--connect", daemon.endpoint, "--speed", "0", "--drop", "gaps:left-arm,right-leg",
                 "--out", str(out), "--json", str(tmp_path / "f.json"), "--plot", str(tmp_path / "f.png"), "-q"]) == 0
    text = capsys.readouterr().out
    assert "within 2 reported std" in text and "first dropped frame: median error" in text
    rep = json.loads((tmp_path / "f.json").read_text())
    fig = rep["figures"]
    truth = read_amc(src)
    keep, _ = drop_mask("gaps:left-arm,right-leg", truth, 0)
    got = read_amc(str(out), find_asf(src))
    # the same figures computed here from the written take: the daemon's hold model repeats the last value
    # sent, so the written take is the fill (its std is not written: the calibration is checked apart)
    case = make_case("07_01", truth.frames, keep, truth.channels, truth.fps, cm_per_unit(truth.skeleton), "gaps")
    mine = score(case, got.frames, None)
    assert fig["n_rms_deg"] == mine["n_rms_deg"] > 0
    assert fig["rms_deg"] == pytest.approx(mine["rms_deg"], rel=1e-4)
    assert fig["onset_err_median_deg"] == pytest.approx(mine["onset_err_median_deg"], rel=1e-4, abs=1e-4)
    assert fig["rms_deg"] == pytest.approx(rep["accuracy"]["rms_deg"], rel=1e-6)
    # holding the last value: the first 100 ms is hold's own figure, and a std was reported
    assert fig["rms_first_100ms_deg"] == pytest.approx(fig["hold_rms_first_100ms_deg"], rel=1e-3)
    assert 0.0 < fig["within_1std"] <= fig["within_2std"] <= 1.0 and np.isfinite(fig["nll_per_value"])
    assert (tmp_path / "f.png").stat().st_size > 10_000
    assert (tmp_path / "f.latency.png").stat().st_size > 5_000 and "latency histogram:" in text


def test_replay_figures_skip_values_the_take_never_had(daemon, tmp_path):
    """A take with dropouts of its own (a live recording's): the drop pattern's values whose truth the
    recording has are scored; its own gaps are filled but never scored (nothing knows their truth)."""
    import json

    from clients.recording import write_motion_recording
    from mocap.representation import is_angle

    m = load_trial("07_01").slice(0, 240)
    captured = np.ones(m.frames.shape, bool)
    j = m.channels.index("lhumerus.rx")
    captured[100:130, j] = False           # the recording's own dropout: before and inside pan2009's erased half
    src = tmp_path / "holey.lrec"
    write_motion_recording(str(src), m, captured, None)
    assert main(["replay", str(src), "--connect", daemon.endpoint, "--speed", "0", "--drop", "pan2009",
                 "--out", str(tmp_path / "holey.filled.lrec"), "--json", str(tmp_path / "h.json"), "-q"]) == 0
    rep = json.loads((tmp_path / "h.json").read_text())
    keep, _ = drop_mask("pan2009", m)
    ang = np.array([is_angle(c) for c in m.channels])
    n = int((~keep & captured & ang[None, :]).sum())
    assert n == int((~keep & ang[None, :]).sum()) - 10   # lhumerus.rx frames 120-129: erased, never known
    assert rep["figures"]["n_rms_deg"] == rep["accuracy"]["erased_angle_values"] == n
    assert all(np.isfinite(v) for k, v in rep["figures"].items() if k.endswith("_deg") and v is not None)
