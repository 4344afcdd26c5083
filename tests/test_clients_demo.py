"""`lacuna demo` end to end with a real daemon process: on the real data (default, hold and interp
scored by mocap.metrics on a held-out TEST take of another performer) and on the synthetic gait
(the offline path)."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest
from waiting import wait_until

from clients import demo, demo_score, synth
from lacuna.cli import main
from mocap import splits


def test_synthetic_gait_is_a_finite_cmu_shaped_walk():
    g = synth.gait(3.0, seed=5)
    assert g.frames.shape == (360, 62) and g.channels == synth.CMU_CHANNELS
    assert np.isfinite(g.frames).all()
    knee = g.frames[:, g.channels.index("ltibia.rx")]
    assert knee.max() - knee.min() > 30  # the knee bends every cycle
    assert not np.allclose(synth.gait(3.0, seed=6).frames, g.frames)


def test_the_demo_trains_on_no_take_of_the_replayed_performer():
    assert splits.split_of(demo.TEST_TAKE) == "test"
    names = demo.train_takes(demo.TEST_TAKE)
    assert names and all(splits.split_of(t) == "train" for t in names)
    assert demo.performer(demo.TEST_TAKE) == "02"
    assert all(demo.performer(t) not in (None, "02") for t in names)
    acts = {splits.ACTIVITY[t] for t in names}
    assert "nonloco" in acts and "walk" in acts  # locomotion and non-locomotion
    assert not set(names) & set(splits.PAPER_TESTS + splits.VALIDATION + splits.TEST)


def test_score_uses_the_metrics_bins_on_a_hand_made_fill():
    """A constant 2-degree error on a short and a long gap: every RMS is 2, the onset error 2."""
    T, fps = 240, 120.0
    ch = ["lfemur.rx", "root.tx"]
    truth = np.zeros((T, 2))
    truth[:, 0] = np.arange(T) * 0.5  # 0.5 degree per frame
    obs = np.ones((T, 2), bool)
    obs[20:38, 0] = False  # 0.15 s: short
    obs[100:190, 0] = False  # 0.75 s: long
    case = demo_score.make_case("t", truth, obs, ch, fps, None, "hand")
    s = demo_score.score(case, truth + 2.0, np.full((T, 2), 1.5))
    assert s["rms_deg"] == pytest.approx(2.0) and s["n_rms_deg"] == 18 + 90
    assert s["rms_short_deg"] == pytest.approx(2.0) and s["n_rms_short_deg"] == 18
    assert s["rms_long_deg"] == pytest.approx(2.0) and s["n_rms_long_deg"] == 90
    assert s["onset_err_median_deg"] == pytest.approx(2.0)
    assert s["onset_truth_step_median_deg"] == pytest.approx(0.5)
    assert s["within_2std"] == 1.0 and s["within_1std"] == 0.0
    # holding truth[t0-1] is off by 0.5 deg per frame since the gap began
    assert s["hold_rms_first_100ms_deg"] > 0.5
    assert s["by_length"]["0.1-0.25s"]["n"] == 18 and s["by_length"]["0.5-1s"]["n"] == 90
    # no std reported: calibration is n/a, not a made-up number
    assert demo_score.score(case, truth + 2.0, None)["within_2std"] is None
    # a fill following the truth has no pop; one that jumps 5 deg once inside the long gap has one
    assert s["pop_over_2deg"] == 0.0 and s["pop_max_deg"] == pytest.approx(0.0)
    jump = truth + np.where(np.arange(T)[:, None] >= 150, 5.0, 0.0)
    p = demo_score.score(case, jump, None)
    assert p["pop_max_deg"] == pytest.approx(5.0) and p["pop_over_2deg"] == pytest.approx(1 / (17 + 89))


def _check_report(rep: dict, out) -> None:
    for name in ("hold", "interp"):
        assert name in rep["results"]
    for name, r in rep["results"].items():
        s = r["scores"]
        for k in demo_score.FIGURES:
            assert k in s
        assert s["rms_deg"] is not None and np.isfinite(s["rms_deg"]) and s["n_rms_deg"] > 0
        assert s["onset_err_median_deg"] is not None and s["rms_first_100ms_deg"] is not None
        assert r["through_daemon"] == (name != "interp")
        if r["through_daemon"]:
            # the demo's daemon serves overdue frames late instead of dropping them
            assert r["latency"]["p99_ms"] > 0 and r["dropped_frames"] == 0
            # through the daemon the same model gives the offline result unless it degraded
            if r["status"].get("degraded", 0) == 0:
                assert s["rms_deg"] == pytest.approx(r["offline_rms_deg"], rel=1e-3, abs=1e-3)
                if s["nll_per_value"] is not None:  # and the same std (float32 on the wire)
                    assert s["nll_per_value"] == pytest.approx(r["offline_nll_per_value"], rel=1e-3, abs=1e-3)
    for p in rep["plots"].values():
        assert os.path.getsize(p) > 0 and p.endswith(".png")
    assert (out / "demo.json").exists()
    # the daemon was stopped: its log ends with the daemon's own stop line
    assert '"event": "stopped"' in (out / "daemon" / "daemon.log").read_text()


@pytest.mark.slow
@pytest.mark.realdata
def test_demo_on_real_data_replays_a_test_take_of_another_performer(tmp_path, capsys, data):
    out = tmp_path / "demo"
    # --methods default: the small HLM the demo also trains by default takes a minute or more
    assert main(["demo", "--source", "data", "--methods", "default", "--speed", "0", "--out", str(out), "-q"]) == 0
    rep = json.loads((out / "demo.json").read_text())
    assert not rep["motion"].startswith("SYNTHETIC")
    take = rep["take"]["name"]
    assert take == demo.TEST_TAKE and splits.split_of(take) == "test" and rep["take"]["split"] == "test"
    trained = rep["train_takes"]
    assert trained and all(splits.split_of(t) == "train" for t in trained)
    assert rep["take"]["performer"] not in {demo.performer(t) for t in trained}
    assert {"default", "hold", "interp"} == set(rep["results"])
    _check_report(rep, out)
    # short and long dropouts were both replayed and scored
    d = rep["dropouts"]["lengths"]
    assert d["short (0.1-0.25 s)"] >= 1 and d["long (0.5-2 s)"] >= 1
    for r in rep["results"].values():
        assert r["scores"]["n_rms_short_deg"] > 0 and r["scores"]["n_rms_long_deg"] > 0
    # default reports a std: its calibration figures are numbers
    sd = rep["results"]["default"]["scores"]
    assert 0.0 < sd["within_2std"] <= 1.0 and np.isfinite(sd["nll_per_value"])
    text = capsys.readouterr().out
    for word in ("default", "hold", "interp", "in 2sd", "onset", "fills vs truth (2-std band):", "latency histogram:"):
        assert word in text


def test_demo_refuses_a_take_that_is_not_a_test_take(tmp_path, capsys):
    assert main(["demo", "--take", "35_29", "--out", str(tmp_path / "d"), "--speed", "0", "-q"]) == 2
    assert "lacuna: error: --take 35_29" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()


@pytest.mark.slow
def test_demo_on_synthetic_motion_reports_accuracy_latency_and_plots(tmp_path, capsys):
    out = tmp_path / "demo"
    # a method this build does not register is reported and skipped, the demo goes on; an offline
    # method asked for is scored in-process, once
    assert main(["demo", "--source", "synthetic", "--methods", "default,nosuch,interp", "--speed", "0", "--out",
                 str(out), "-q"]) == 0
    rep = json.loads((out / "demo.json").read_text())
    assert rep["motion"].startswith("SYNTHETIC") and rep["take"]["split"] == "synthetic"
    assert {"default", "hold", "interp"} == set(rep["results"])
    assert any(n.startswith("nosuch: not registered") for n in rep["notes"])
    assert sum(n.startswith("interp is offline") for n in rep["notes"]) == 1
    _check_report(rep, out)
    assert "SYNTHETIC" in capsys.readouterr().out


def _sigint_as_in_a_terminal() -> None:
    """The child's SIGINT as a terminal's foreground job has it.  A command started in the background
    by a shell without job control (``pytest ... &`` in a script, as the README's test command often
    is) inherits SIGINT ignored, and Python then installs no KeyboardInterrupt for it: the demo
    ignored this test's Ctrl-C and replayed on (the stacks at SIGABRT showed it in its replay loop)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.slow
@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_demo_ctrl_c_stops_the_daemon_it_started(tmp_path, sig):
    """Ctrl-C, or a SIGTERM (a ``kill``, a CI timeout), ends the demo with the daemon it started."""
    import signal
    import subprocess
    import sys

    out = tmp_path / "demo"
    # PYTHONFAULTHANDLER: a demo that outlives its signal is sent SIGABRT below, which dumps every
    # thread's stack into its stderr, and the failure shows where it was stuck
    p = subprocess.Popen([sys.executable, "-m", "lacuna.cli", "demo", "--source", "synthetic", "--methods", "none",
                          "--speed", "0.1", "--out", str(out), "-q"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         env=dict(os.environ, PYTHONFAULTHANDLER="1"), preexec_fn=_sigint_as_in_a_terminal)
    log = out / "daemon" / "daemon.log"
    pid = None
    try:
        def replaying() -> bool:  # the replay is under way (or the demo ended early: reported below)
            return p.poll() is not None or (log.exists() and "stream_hello" in log.read_text())

        wait_until(replaying, 60, "the demo's replay to start", 0.2)
        assert p.poll() is None, "the demo ended before its replay"
        pid = next(json.loads(x) for x in log.read_text().splitlines() if '"ready"' in x)["pid"]
        p.send_signal(getattr(signal, sig))
        try:
            p.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            p.send_signal(signal.SIGABRT)
            _, err = p.communicate(timeout=30)
            pytest.fail(f"the demo did not exit within 30 s of its {sig}; its stderr (stacks at SIGABRT):\n"
                        + err.decode(errors="replace")[-6000:] + "\ndaemon log tail:\n" + log.read_text()[-2000:])
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130  # lacuna: interrupted
    assert '"event": "stopped"' in log.read_text()
    assert not os.path.exists(f"/proc/{pid}") or "zombie" in open(f"/proc/{pid}/status").read().lower()


def test_band_channels_pick_one_moving_dropped_channel_per_group(tmp_path):
    from clients import replay as rp
    from mocap.protocols import GAP_GROUPS, bone

    g = synth.gait(4.0, seed=3)
    obs, bursts = demo.drop_mask(demo.DROP, g, 2)
    cols = rp.band_channels(g.frames, ~obs, g.channels, GAP_GROUPS)
    assert 1 <= len(cols) <= 4
    groups = [next(k for k, b in GAP_GROUPS.items() if bone(g.channels[j]) in b) for j in cols]
    assert len(set(groups)) == len(groups)  # one per joint group
    for j in cols:
        assert (~obs[:, j]).any() and g.frames[:, j].std() > 0
    std = np.full(g.frames.shape, 2.0)
    p = rp.plot_fill_band(str(tmp_path / "f.png"), g.frames, g.frames + 1, std, ~obs, g.channels, g.fps, cols,
                          {"hold": g.frames - 1}, "default", "t")
    assert os.path.getsize(p) > 0
