"""`lacuna demo` end to end on the synthetic gait (the offline path), with a real daemon process."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from clients import synth
from lacuna.cli import main


def test_synthetic_gait_is_a_finite_cmu_shaped_walk():
    g = synth.gait(3.0, seed=5)
    assert g.frames.shape == (360, 62) and g.channels == synth.CMU_CHANNELS
    assert np.isfinite(g.frames).all()
    knee = g.frames[:, g.channels.index("ltibia.rx")]
    assert knee.max() - knee.min() > 30  # the knee bends every cycle
    assert not np.allclose(synth.gait(3.0, seed=6).frames, g.frames)


@pytest.mark.slow
def test_demo_on_synthetic_motion_reports_accuracy_latency_and_plots(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--source", "synthetic", "--speed", "0", "--out", str(out), "-q"]) == 0
    rep = json.loads((out / "demo.json").read_text())
    assert rep["motion"].startswith("SYNTHETIC")
    assert {"hold", "nn"} <= set(rep["results"])
    for name, r in rep["results"].items():
        assert r["accuracy"]["erased_angle_values"] > 0
        assert np.isfinite(r["accuracy"]["rms_deg"]) and r["latency"]["p99_ms"] > 0
        # through the daemon the same model gives the offline result unless it degraded
        if r["status"].get("degraded", 0) == 0:
            assert r["accuracy"]["rms_deg"] == pytest.approx(r["offline_rms_deg"], rel=1e-3, abs=1e-3)
    for p in rep["plots"].values():
        assert os.path.getsize(p) > 0
    text = capsys.readouterr().out
    assert "fills vs truth:" in text and "latency histogram:" in text
    # the daemon was stopped: its log ends with the daemon's own stop line
    log = (out / "daemon" / "daemon.log").read_text()
    assert '"event": "stopped"' in log


@pytest.mark.slow
def test_demo_ctrl_c_stops_the_daemon_it_started(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "demo"
    p = subprocess.Popen([sys.executable, "-m", "lacuna.cli", "demo", "--source", "synthetic", "--methods", "none",
                          "--speed", "0.5", "--out", str(out), "-q"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    log = out / "daemon" / "daemon.log"
    pid = None
    try:
        deadline = time.monotonic() + 60
        while pid is None and time.monotonic() < deadline and p.poll() is None:
            time.sleep(0.2)
            if log.exists() and "stream_hello" in log.read_text():  # the replay is under way
                ready = [json.loads(x) for x in log.read_text().splitlines() if '"ready"' in x]
                pid = ready[0]["pid"]
        assert pid is not None, "the demo never got to its replay"
        p.send_signal(signal.SIGINT)
        p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130  # lacuna: interrupted
    assert '"event": "stopped"' in log.read_text()
    assert not os.path.exists(f"/proc/{pid}") or "zombie" in open(f"/proc/{pid}/status").read().lower()
