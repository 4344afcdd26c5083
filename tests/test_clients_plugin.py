"""The plugin library against a real `lacuna serve` process on loopback (issue 6, item 1 and 6).

Model: hold-last-value fitted on real CMU frames, so every filled value is predictable (the
last observed value of that channel, or the training mean before any), which lets the tests
check the channel mapping value by value.
"""
from __future__ import annotations

import asyncio

import numpy as np
import pytest

from clients import Client, DaemonUnavailable
from clients.aio import AsyncClient
from clients.configfile import free_port
from clients.harness import DaemonProcess
from daemon import wire
from mocap.baselines import HoldModel
from mocap.datasets import load_trial

EXTRA = "studio.quality"


@pytest.fixture(scope="module")
def hold_file(tmp_path_factory, data):
    m = load_trial("07_02")
    f = tmp_path_factory.mktemp("models") / "hold.npz"
    model = HoldModel.fit([m.frames], m.channels)
    model.save(str(f))
    return str(f), model


@pytest.fixture(scope="module")
def daemon(hold_file, tmp_path_factory):
    d = DaemonProcess({"hold": hold_file[0]}, workdir=str(tmp_path_factory.mktemp("daemon")),
                      daemon={"budget_ms": 200.0})
    d.start()
    yield d
    d.stop()


def studio_take(model_channels: list[str]) -> tuple[list[str], np.ndarray]:
    """The studio's names: the model's channels in reverse order, minus root.tx, plus one extra
    channel the model lacks.  Frames (T, C) from CMU 07_01 in that order, extra = 42."""
    m = load_trial("07_01")
    names = [c for c in reversed(model_channels) if c != "root.tx"] + [EXTRA]
    frames = np.column_stack([m.frames[:, m.index(names[:-1])], np.full(m.n_frames, 42.0)])
    return names, frames


def check_fill(reply, k: int, sent: np.ndarray, obs: np.ndarray, held: np.ndarray) -> None:
    assert isinstance(reply, wire.FillMsg), reply
    assert reply.seq == k
    assert reply.status == "ok"
    got = np.asarray(reply.angles, np.float64)
    np.testing.assert_array_equal(got[obs], sent[obs].astype(np.float32))
    np.testing.assert_array_equal(reply.filled[:-1], ~obs[:-1])
    assert not reply.filled[-1], "a channel the model lacks must never be marked filled"
    np.testing.assert_allclose(got[~obs], held[~obs], atol=1e-4)


def test_plugin_round_trip_with_studio_names(daemon, hold_file):
    _, model = hold_file
    names, frames = studio_take(model.channels)
    idx = {c: i for i, c in enumerate(model.channels)}
    mean = np.array([model.mean_[idx[c]] if c in idx else np.nan for c in names])
    arm = np.array([c.startswith(("lhumerus", "lradius")) for c in names])
    with Client(daemon.endpoint, "rt-1", names, timeout_s=5.0) as c:
        ack = c.hello()
        assert ack.model == "hold"
        assert ack.passthrough == [EXTRA] and ack.missing == ["root.tx"]
        held = mean.copy()
        for k in range(12):
            obs = np.ones(len(names), bool)
            if 3 <= k < 9:
                obs &= ~arm
            reply = c.fill(frames[k], obs, t=k / 120.0)
            check_fill(reply, k, frames[k], obs, held)
            assert reply.t == pytest.approx(k / 120.0)
            held = np.where(obs, frames[k].astype(np.float32), held)
    st = Client(daemon.endpoint, "rt-probe").status()
    assert st["streams"]["rt-1"]["frames_out"] == 12


def test_pipelined_sends_match_answers_by_seq(daemon, hold_file):
    _, model = hold_file
    names, frames = studio_take(model.channels)
    with Client(daemon.endpoint, "rt-pipe", names, timeout_s=5.0) as c:
        seqs = [c.send(frames[k]) for k in range(20)]
        got = {}
        while len(got) < len(seqs):
            msg = c.recv(5.0)
            assert msg is not None, f"answers missing for {sorted(set(seqs) - set(got))}"
            got[msg.seq] = msg
    assert sorted(got) == seqs
    served = [m for m in got.values() if isinstance(m, wire.FillMsg)]
    assert served and all(isinstance(m, (wire.FillMsg, wire.Drop)) for m in got.values())
    # the newest frame is always served (conflation keeps the newest)
    assert isinstance(got[seqs[-1]], wire.FillMsg)
    np.testing.assert_array_equal(got[seqs[-1]].angles, frames[19].astype(np.float32))


def test_asyncio_client_round_trip(daemon, hold_file):
    _, model = hold_file
    names, frames = studio_take(model.channels)
    obs = np.ones(len(names), bool)
    obs[:5] = False

    async def go():
        async with AsyncClient(daemon.endpoint, "rt-async", names, timeout_s=5.0) as c:
            ack = await c.hello()
            r0 = await c.fill(frames[0])
            r1 = await c.fill(frames[1], obs)
            st = await c.status()
            return ack, r0, r1, st

    ack, r0, r1, st = asyncio.run(go())
    assert st["streams"]["rt-async"]["frames_out"] == 2
    assert ack.passthrough == [EXTRA]
    assert r0.seq == 0 and r1.seq == 1
    np.testing.assert_array_equal(r1.filled[:5], True)
    # hold: the filled values are frame 0's
    np.testing.assert_array_equal(r1.angles[:5], frames[0, :5].astype(np.float32))


def test_reconnect_after_daemon_restart_keeps_stream_handshake_and_seq(hold_file, tmp_path):
    _, model = hold_file
    names, frames = studio_take(model.channels)
    d = DaemonProcess({"hold": hold_file[0]}, workdir=str(tmp_path), daemon={"budget_ms": 200.0})
    d.start()
    try:
        c = Client(d.endpoint, "actor", names, timeout_s=2.0, retries=5)
        for k in range(5):
            assert isinstance(c.fill(frames[k]), wire.FillMsg)
        d.kill()  # a crash, not a clean stop
        d.start()  # same port
        obs = np.ones(len(names), bool)
        obs[:4] = False
        r = c.fill(frames[5], obs)
        # the new daemon got the handshake again: the studio order still maps correctly and the
        # filled values are the fresh state's training means (the old process's state is gone)
        assert isinstance(r, wire.FillMsg) and r.seq == 5
        idx = {ch: i for i, ch in enumerate(model.channels)}
        mean = np.array([model.mean_[idx[ch]] for ch in names[:4]])
        np.testing.assert_allclose(r.angles[:4], mean, atol=1e-4)
        np.testing.assert_array_equal(r.angles[4:-1], frames[5, 4:-1].astype(np.float32))
        assert r.filled[:4].all() and not r.filled[4:].any()
        assert c.session.disconnects >= 1 and c.session.next_seq == 6
        st = c.status()["streams"]["actor"]
        assert st["frames_out"] == 1 and st["passthrough"] == 1 and st["missing"] == 1
        c.close()
    finally:
        d.stop()


def test_no_daemon_raises_after_retries():
    port = free_port()
    with Client(f"tcp://127.0.0.1:{port}", "nobody", timeout_s=0.2, retries=1) as c:
        with pytest.raises(DaemonUnavailable, match="no answer"):
            c.fill(np.zeros(3))
        assert c.session.reconnects == 1


def test_close_does_not_wait_on_a_socket_an_interrupted_open_left_behind(daemon, hold_file):
    """A Ctrl-C inside ``_open`` (the socket made, not yet kept) leaves a socket of the client's own
    context that only the traceback holds; ``close`` must still end the context (``term()`` alone
    waits for every socket forever) and give the stream up."""
    import threading

    import zmq

    model = hold_file[1]
    c = Client(daemon.endpoint, "orphaned", model.channels, timeout_s=2.0)
    c.fill(np.zeros(len(model.channels)))
    orphan = c.ctx.socket(zmq.DEALER)   # what the interrupted open leaves: open, referenced, never closed
    orphan.connect(daemon.endpoint)
    done = threading.Event()
    t = threading.Thread(target=lambda: (c.close(), done.set()), daemon=True)
    t.start()
    t.join(20)
    assert done.is_set(), "Client.close hung on a socket of its own context it did not know of"
    assert orphan.closed and c.ctx.closed
    # the stream was released: a second client owns it at once (no idle wait), with no claim of its own
    with Client(daemon.endpoint, "orphaned", model.channels, timeout_s=2.0) as c2:
        assert c2.fill(np.zeros(len(model.channels))).seq == 0


def test_bad_frames_are_refused_before_sending(daemon):
    with Client(daemon.endpoint, "bad", ["a", "b"], timeout_s=1.0) as c:
        with pytest.raises(ValueError, match="2 channels; frame has 3"):
            c.fill(np.zeros(3))
        with pytest.raises(ValueError, match="observed mask"):
            c.fill(np.zeros(2), np.ones(3, bool))


def test_asyncio_client_reconnects_after_daemon_restart(hold_file, tmp_path):
    _, model = hold_file
    names, frames = studio_take(model.channels)
    d = DaemonProcess({"hold": hold_file[0]}, workdir=str(tmp_path), daemon={"budget_ms": 200.0})
    d.start()

    async def go():
        async with AsyncClient(d.endpoint, "aactor", names, timeout_s=2.0, retries=5) as c:
            for k in range(3):
                assert isinstance(await c.fill(frames[k]), wire.FillMsg)
            d.kill()
            d.start()
            obs = np.ones(len(names), bool)
            obs[:4] = False
            r = await c.fill(frames[3], obs)
            return r, c.session

    try:
        r, session = asyncio.run(go())
        st = Client(d.endpoint, "probe").status()["streams"]["aactor"]
    finally:
        d.stop()
    assert isinstance(r, wire.FillMsg) and r.seq == 3
    # the new daemon got the handshake: studio order, the extra channel passed through
    assert st["passthrough"] == 1 and st["missing"] == 1
    idx = {ch: i for i, ch in enumerate(model.channels)}
    np.testing.assert_allclose(r.angles[:4], [model.mean_[idx[ch]] for ch in names[:4]], atol=1e-4)
    np.testing.assert_array_equal(r.angles[4:-1], frames[3, 4:-1].astype(np.float32))
    assert session.disconnects >= 1 and session.next_seq == 4


def test_capture_client_sends_performers_as_one_bundle_and_survives_a_restart(hold_file, tmp_path):
    """CaptureClient: three performers (studio names, the model's own list, a stream the daemon
    refuses frame by frame) in one bundle per instant; each gets its own answer, equal to what a
    one-stream Client gets for the same frame.  After a daemon crash and restart every stream's
    handshake is sent again and the sequence numbers go on."""
    from clients import CaptureClient

    _, model = hold_file
    names, frames = studio_take(model.channels)
    C = len(model.channels)
    d = DaemonProcess({"hold": hold_file[0]}, workdir=str(tmp_path), daemon={"budget_ms": 200.0})
    d.start()
    try:
        obs = np.ones(len(names), bool)
        obs[:4] = False
        own = np.asarray(model.mean_, np.float64) + 1.0
        with CaptureClient(d.endpoint, {"a1": names, "a2": None}, timeout_s=2.0, retries=5) as cap, \
                Client(d.endpoint, "solo", names, timeout_s=2.0) as solo:
            for k in range(3):
                out = cap.fill({"a1": (frames[k], obs), "a2": own})
                assert set(out) == {"a1", "a2"} and out["a1"].seq == out["a2"].seq == k
                ref = solo.fill(frames[k], obs)
                np.testing.assert_array_equal(out["a1"].angles, ref.angles)
                np.testing.assert_array_equal(out["a1"].filled, ref.filled)
                np.testing.assert_array_equal(out["a2"].angles, own.astype(np.float32))
            # a frame of the wrong width for a2's stream is that stream's error, a1 is served
            out = cap.fill({"a1": frames[3], "a2": np.zeros(C + 1)})
            assert isinstance(out["a1"], wire.FillMsg) and isinstance(out["a2"], wire.ErrorMsg)
            assert out["a2"].reason == "width"
            with pytest.raises(ValueError, match="not opened"):
                cap.fill({"stranger": frames[4]})
            d.kill()
            d.start()
            out = cap.fill({"a1": (frames[5], obs), "a2": own})
            assert isinstance(out["a1"], wire.FillMsg) and out["a1"].seq == out["a2"].seq == 4   # numbering goes on
            assert out["a1"].filled[:4].all() and not out["a1"].filled[-1]   # studio names mapped again
            st = cap.status()["streams"]
            assert st["a1"]["frames_out"] == 1 and st["a1"]["passthrough"] == 1   # the new daemon got a hello
            assert st["a2"]["frames_out"] == 1
    finally:
        d.stop()
