"""`lacuna bridge` over real UDP sockets, with and without a real daemon behind it (issue 6)."""
from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_message_builder import OscMessageBuilder

from clients.bridge import Bridge
from clients.configfile import free_port
from clients.harness import DaemonProcess
from mocap.baselines import HoldModel

CH = ["lfemur.rx", "lfemur.ry", "ltibia.rx", "rfemur.rx", "rtibia.rx"]
RECV_S = 5.0


def osc_frame(stream: str, seq: int, t: float, values) -> bytes:
    b = OscMessageBuilder("/lacuna/frame")
    b.add_arg(stream, "s")
    b.add_arg(seq, "i")
    b.add_arg(t, "d")
    for v in values:
        b.add_arg(float(v), "f")
    return b.build().dgram


def osc_hello(stream: str, channels: list[str]) -> bytes:
    b = OscMessageBuilder("/lacuna/hello")
    b.add_arg(stream, "s")
    b.add_arg("", "s")
    for c in channels:
        b.add_arg(c, "s")
    return b.build().dgram


@pytest.fixture
def pipeline():
    """A UDP socket standing for the rest of the pipeline, and one for the capture system."""
    down = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    down.bind(("127.0.0.1", 0))
    down.settimeout(RECV_S)
    cap = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    yield down, cap
    down.close()
    cap.close()


@pytest.fixture
def run_bridge():
    started: list[tuple[Bridge, threading.Thread]] = []

    def start(endpoint: str, send, **kw) -> Bridge:
        b = Bridge(endpoint, ("127.0.0.1", 0), send, **kw)
        t = threading.Thread(target=b.serve_forever, daemon=True)
        t.start()
        started.append((b, t))
        return b

    yield start
    for b, t in started:
        b.stop_flag = True
        t.join(5)
        assert not t.is_alive(), "bridge loop did not stop"
        b.close()


def hold_daemon(tmp_path) -> DaemonProcess:
    """A started daemon serving a hold-last-value model "hold" (7 +- 1 on every channel)."""
    model = tmp_path / "hold.npz"
    HoldModel(CH, np.full(len(CH), 7.0), np.full(len(CH), 1.0)).save(str(model))
    d = DaemonProcess({"hold": str(model)}, workdir=str(tmp_path / "d"), daemon={"budget_ms": 200.0})
    d.start()
    return d


def next_fill(down: socket.socket) -> dict:
    """Read datagrams until a fill bundle; returns its /lacuna/fill and /lacuna/filled contents."""
    while True:
        data, _ = down.recvfrom(1 << 16)
        if not OscBundle.dgram_is_bundle(data):
            continue
        parts = {m.address: m.params for m in OscBundle(data)}
        f = parts["/lacuna/fill"]
        return {"stream": f[0], "seq": f[1], "status": f[3], "model": f[4], "values": np.array(f[7:], np.float32),
                "filled": np.frombuffer(parts["/lacuna/filled"][2], np.uint8).astype(bool)}


def test_bridge_passes_frames_through_flagged_when_the_daemon_is_down(pipeline, run_bridge):
    down, cap = pipeline
    b = run_bridge(f"tcp://127.0.0.1:{free_port()}", down.getsockname(), timeout_s=0.05, probe_s=60.0)
    vals = np.array([1.5, np.nan, -3.25, 10.0, 0.0], np.float32)
    for k in range(3):
        cap.sendto(osc_frame("actor", k, k / 120.0, vals + k), b.address)
        f = next_fill(down)
        assert (f["stream"], f["seq"], f["status"], f["model"]) == ("actor", k, "passthrough", "")
        np.testing.assert_array_equal(f["values"], vals + k)  # NaN where it was missing, untouched
        assert not f["filled"].any()
    assert b.counts.passed_through == 3 and b.counts.filled == 0


def test_bridge_fills_then_passes_through_while_daemon_is_away_then_fills_again(pipeline, run_bridge, tmp_path):
    down, cap = pipeline
    d = hold_daemon(tmp_path)
    try:
        b = run_bridge(d.endpoint, down.getsockname(), timeout_s=0.3, probe_s=0.2,
                       record=str(tmp_path / "{stream}.lrec"))
        cap.sendto(osc_hello("actor", CH), b.address)
        vals = np.array([1.0, np.nan, 2.0, 3.0, 4.0], np.float32)
        cap.sendto(osc_frame("actor", 0, 0.0, vals), b.address)
        f = next_fill(down)
        assert f["status"] == "ok" and f["model"] == "hold"
        assert f["values"][1] == pytest.approx(7.0) and f["filled"].tolist() == [False, True, False, False, False]

        d.kill()
        cap.sendto(osc_frame("actor", 1, 1 / 120, vals), b.address)
        f = next_fill(down)
        assert f["status"] == "passthrough" and np.isnan(f["values"][1]) and not f["filled"].any()

        d.start()  # same port
        deadline = time.monotonic() + 20
        k = 2
        while True:  # frames pass through until the next probe finds the daemon back
            cap.sendto(osc_frame("actor", k, k / 120, vals), b.address)
            f = next_fill(down)
            if f["status"] == "ok" or time.monotonic() > deadline:
                break
            assert f["status"] == "passthrough"
            k += 1
            time.sleep(0.05)  # (pacing the probe frames, not waiting: the loop ends on the event, a fill `ok`)
        assert f["status"] == "ok" and f["seq"] == k and f["filled"][1]
    finally:
        d.stop()
    # --record kept every frame it emitted, raw and filled, pass-through ones included
    from clients.recording import read_recording

    rec = read_recording(str(tmp_path / "actor.lrec"))
    assert rec.channels == CH and rec.seq.tolist() == list(range(k + 1))
    assert rec.status[0] == "ok" and rec.status[1] == "passthrough" and rec.status[-1] == "ok"
    np.testing.assert_array_equal(rec.observed[:, 1], False)


def test_bridge_rejects_garbage_and_keeps_serving(pipeline, run_bridge):
    down, cap = pipeline
    b = run_bridge(f"tcp://127.0.0.1:{free_port()}", down.getsockname(), timeout_s=0.05, probe_s=60.0)
    cap.sendto(b"\x00not osc", b.address)
    data, _ = down.recvfrom(1 << 16)
    assert data.startswith(b"/lacuna/error")
    cap.sendto(osc_frame("actor", 0, 0.0, [1.0]), b.address)
    assert next_fill(down)["status"] == "passthrough"
    assert b.counts.rejected == 1


def test_bridge_takes_an_osc_bundle_of_performers(pipeline, run_bridge, tmp_path):
    """A capture tool that sends each instant as one OSC bundle: every message in it is
    handled as if it had come alone; a malformed one gets its own error."""
    down, cap = pipeline
    d = hold_daemon(tmp_path)
    try:
        b = run_bridge(d.endpoint, down.getsockname(), timeout_s=2.0, probe_s=0.2)
        vals = np.array([1.0, np.nan, 2.0, 3.0, 4.0], np.float32)
        els = [osc_frame("a1", 0, 0.0, vals), b"/lacuna/bogus\x00\x00\x00,\x00\x00\x00", osc_frame("a2", 0, 0.0, vals)]
        cap.sendto(b"#bundle\x00" + b"\x00" * 7 + b"\x01" + b"".join(len(e).to_bytes(4, "big") + e for e in els), b.address)
        fills, errors = {}, []
        while len(fills) + len(errors) < 3:
            data, _ = down.recvfrom(1 << 16)
            if OscBundle.dgram_is_bundle(data):
                f = {m.address: m.params for m in OscBundle(data)}["/lacuna/fill"]
                fills[f[0]] = f
            else:
                errors.append(data)
        assert sorted(fills) == ["a1", "a2"] and all(f[3] == "ok" and f[8] == pytest.approx(7.0) for f in fills.values())
        assert len(errors) == 1 and errors[0].startswith(b"/lacuna/error")
        assert b.counts.filled == 2 and b.counts.rejected == 1
    finally:
        d.stop()
