"""Joint positions in the daemon's fills, on request (hello ``positions: true``).

A real daemon process serves an HLM model trained by ``lacuna train hlm`` (tiny settings, on
35_01.amc) and a hold model (no skeleton); clients send the first frames of 35_08.amc, left arm
missing.  The positions a client gets are checked against forward
kinematics computed here, independently, from the take's own ASF (``Kinematics.from_motion``, the
numpy batch code, not the compiled per-frame code the daemon runs) on the completed frames the
daemon returned.
"""
from __future__ import annotations

import msgpack
import numpy as np
import pytest
import zmq

from clients.client import Client
from clients.configfile import free_port
from clients.harness import DaemonProcess
from clients.session import DaemonRefused
from daemon import wire
from lacuna.cli import main
from mocap.baselines import HoldModel
from mocap.fk import Kinematics
from mocap.io import read_motion

pytestmark = pytest.mark.realdata
TINY_HLM = ["--styles", "1", "--restarts", "1", "--iterations", "3", "-N", "120", "-q"]
ARM = ("lhumerus", "lradius", "lwrist", "lhand", "lfingers", "lthumb")


@pytest.fixture(scope="module")
def served(data, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("positions")
    assert main(["train", "hlm", str(data / "cmu" / "35" / "35_01.amc"), "-o", str(tmp / "hlm.npz"), *TINY_HLM]) == 0
    take = read_motion(data / "cmu" / "35" / "35_08.amc")
    HoldModel(list(take.channels), np.zeros(len(take.channels)), np.ones(len(take.channels))).save(str(tmp / "hold.npz"))
    d = DaemonProcess({"hlm": tmp / "hlm.npz", "hold": tmp / "hold.npz"}, "hlm", workdir=str(tmp / "d"),
                      daemon={"budget_ms": 1000.0}, osc={"listen": f"127.0.0.1:{free_port()}"}).start(120)
    yield d, take
    d.stop()


def _frames(take, n=40):
    sent = take.frames[:n].astype(np.float32)
    miss = np.array([c.split(".")[0] in ARM for c in take.channels])
    sent[:, miss] = np.nan
    return sent, miss


def test_a_client_asking_gets_the_positions_of_the_completed_frames(served):
    d, take = served
    kin = Kinematics.from_motion(take)  # from the take's own ASF file, numpy batch FK
    sent, miss = _frames(take)
    with Client(d.endpoint, "pos", list(take.channels), positions=True, timeout_s=30) as c:
        ack = c.hello()
        assert ack.joints == kin.joints and ack.parents == kin.parents
        assert c.joints == kin.joints and c.parents == kin.parents
        got, done = [], []
        for t in range(len(sent)):
            m = c.fill(sent[t])
            assert isinstance(m, wire.FillMsg) and m.status == "ok", m
            assert m.filled[miss].all()
            assert m.positions is not None and m.positions.dtype == np.float32
            assert m.positions.shape == (len(kin.joints), 3)
            got.append(m.positions)
            done.append(m.angles)
    want = kin.positions(np.array(done, dtype=np.float64))
    np.testing.assert_allclose(np.array(got), want, atol=1e-5, rtol=0)
    # the filled arm moved the left hand: positions are those of the fills, not of a rest pose or the sent NaNs
    hand = kin.joints.index("lhand")
    assert np.isfinite(np.array(got)).all()
    assert np.ptp(np.array(got)[:, hand], axis=0).max() > 0.01


def test_positions_follow_the_model_channels_through_a_studio_reordering(served):
    """A studio that sends the model's channels in another order plus one of its own: positions
    are of the model-space frame (the passthrough channel plays no part)."""
    d, take = served
    kin = Kinematics.from_motion(take)
    sent, miss = _frames(take, 20)
    order = np.arange(len(take.channels))[::-1]
    studio = [take.channels[i] for i in order] + ["studio.extra"]
    with Client(d.endpoint, "pos-reordered", studio, positions=True, timeout_s=30) as c:
        ack = c.hello()
        assert ack.passthrough == ["studio.extra"] and ack.joints == kin.joints
        got, done = [], []
        for t in range(len(sent)):
            m = c.fill(np.append(sent[t][order], np.float32(7.0)))
            got.append(m.positions)
            done.append(np.asarray(m.angles[:-1])[np.argsort(order)])  # back to the model's order
    np.testing.assert_allclose(np.array(got), kin.positions(np.array(done, np.float64)), atol=1e-5, rtol=0)


def test_streams_of_one_bundle_each_get_their_own_positions_or_none(served, data):
    """Four streams in one `frames` bundle (served together: the (n, C) reply path), three asking
    for positions; the fourth's replies carry no `positions` key on the wire at all."""
    d, take = served
    kin = Kinematics.from_motion(take)
    sent, _ = _frames(take, 12)
    ctx = zmq.Context()
    s = ctx.socket(zmq.DEALER)
    s.setsockopt(zmq.LINGER, 0)
    s.connect(d.endpoint)
    try:
        sids = [f"b{i}" for i in range(4)]
        for i, sid in enumerate(sids):
            s.send(wire.encode(wire.Hello(sid, list(take.channels), positions=i < 3)))
            assert s.poll(10000)
            ack = wire.decode(s.recv())
            assert isinstance(ack, wire.HelloAck), ack
            assert (ack.joints == kin.joints) if i < 3 else (ack.joints is None)
        for t in range(len(sent)):
            # each stream its own frame: the take shifted by i frames
            frames = [wire.Frame(sid, t, t / 120.0, sent[(t + i) % len(sent)]) for i, sid in enumerate(sids)]
            s.send(wire.encode(wire.Bundle(frames)))
            answers = {}
            while len(answers) < 4:
                assert s.poll(10000), "no replies"
                raw = msgpack.unpackb(s.recv(), raw=False)
                for r in raw["replies"] if raw["type"] == "replies" else [raw]:
                    answers[r["stream"]] = r
            for i, sid in enumerate(sids):
                r = answers[sid]
                assert r["type"] == "fill", r
                if i == 3:
                    assert "positions" not in r
                    continue
                m = wire.decode(msgpack.packb(r, use_bin_type=True))
                want = kin.positions(m.angles.astype(np.float64)[None])[0]
                np.testing.assert_allclose(m.positions, want, atol=1e-5, rtol=0)
    finally:
        s.close(0)
        ctx.term()


def test_a_client_not_asking_gets_no_positions(served):
    d, take = served
    sent, _ = _frames(take, 3)
    with Client(d.endpoint, "plain", list(take.channels), timeout_s=30) as c:
        assert c.hello().joints is None and c.joints is None
        for t in range(len(sent)):
            m = c.fill(sent[t])
            assert isinstance(m, wire.FillMsg) and m.status == "ok" and m.positions is None


def test_a_model_without_a_skeleton_refuses_positions_with_no_skeleton(served):
    d, take = served
    with Client(d.endpoint, "held", list(take.channels), model="hold", positions=True, timeout_s=30) as c:
        with pytest.raises(DaemonRefused) as e:
            c.hello()
    assert e.value.error.reason == "no_skeleton"
    assert "'hold'" in e.value.error.detail and "no training skeleton" in e.value.error.detail
    # the refusal left no stream behind and the daemon serves on
    with Client(d.endpoint, "held", list(take.channels), model="hold", timeout_s=30) as c:
        assert c.hello().model == "hold"
        assert c.fill(take.frames[0]).status == "ok"



def test_a_reload_keeps_a_positions_stream_on_a_model_with_a_skeleton_only(served):
    """In-process SessionTable: a reload swapping the model rebinds a stream that asked for
    positions when the new model has a skeleton (its FK rebuilt), and keeps the old model (and
    positions) when the new one has none, rather than silently dropping the positions."""
    from daemon.sessions import SessionTable
    from lacuna.modelfile import load_model

    d, take = served
    hlm = load_model(d.config()["models.hlm"]["file"])
    models = {"hlm": hlm}
    table = SessionTable(lambda name, sid: (name or "hlm", models[name or "hlm"]), 8, lambda *a: None)
    ack, _ = table.hello(wire.Hello("r", list(take.channels), positions=True))
    s = table.sessions["r"]
    assert ack.joints and s.fk is not None and s.fk.kin.channels == list(hlm.channels)
    hlm2 = load_model(d.config()["models.hlm"]["file"])  # the same file read again: a new model object
    assert table.rebind("hlm", hlm2) == 1 and s.model is hlm2 and s.fk is not None
    hold = load_model(d.config()["models.hold"]["file"])
    assert table.rebind("hlm", hold) == 0 and s.model is hlm2 and s.fk is not None
    plain, _ = table.hello(wire.Hello("p", list(take.channels)))
    assert plain.joints is None and table.sessions["p"].fk is None
    assert table.rebind("hlm", hold) == 1 and table.sessions["p"].model is hold


def test_the_asyncio_client_asks_for_positions_too(served):
    import asyncio

    from clients.aio import AsyncClient

    d, take = served
    kin = Kinematics.from_motion(take)
    sent, _ = _frames(take, 5)

    async def run():
        async with AsyncClient(d.endpoint, "pos-aio", list(take.channels), timeout_s=30, positions=True) as c:
            assert (await c.hello()).joints == kin.joints
            return [await c.fill(f) for f in sent]

    for m in asyncio.run(run()):
        np.testing.assert_allclose(m.positions, kin.positions(m.angles.astype(np.float64)[None])[0], atol=1e-5, rtol=0)


def _osc_parts(dgram):
    """An OSC datagram -> {address: params} (a bundle's messages, or the one message)."""
    from pythonosc.osc_bundle import OscBundle
    from pythonosc.osc_message import OscMessage

    if OscBundle.dgram_is_bundle(dgram):
        return {m.address: list(m.params) for m in OscBundle(dgram)}
    m = OscMessage(dgram)
    return {m.address: list(m.params)}


def _osc_msg(address, args):
    from pythonosc.osc_message_builder import OscMessageBuilder

    b = OscMessageBuilder(address)
    for v, t in args:
        b.add_arg(v, t)
    return b.build().dgram


def test_osc_hello_positions_gets_joints_and_positions_in_every_fill(served):
    """Over a real UDP socket: ``/lacuna/hello/positions`` is acked with the joints and parents,
    and each fill bundle carries ``/lacuna/positions`` (x y z per joint), equal to the take's own
    ASF FK (numpy batch code) on the completed frame the same bundle returns."""
    import socket

    d, take = served
    kin = Kinematics.from_motion(take)
    sent, miss = _frames(take, 15)
    host, port = d.osc_opts["listen"].rsplit(":", 1)
    u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    u.settimeout(30)
    try:
        u.sendto(_osc_msg("/lacuna/hello/positions", [("osc-pos", "s"), ("", "s")] + [(c, "s") for c in take.channels]),
                 (host, int(port)))
        ack = _osc_parts(u.recv(65536))
        assert ack["/lacuna/hello-ack"][:2] == ["osc-pos", "hlm"], ack
        assert ack["/lacuna/joints"] == ["osc-pos"] + kin.joints
        assert ack["/lacuna/parents"] == ["osc-pos"] + kin.parents
        got, done = [], []
        for t in range(len(sent)):
            u.sendto(_osc_msg("/lacuna/frame", [("osc-pos", "s"), (t, "i"), (t / 120.0, "d")]
                              + [(float(v), "f") for v in sent[t]]), (host, int(port)))
            fill = _osc_parts(u.recv(65536))
            f = fill["/lacuna/fill"]
            assert f[:5] == ["osc-pos", t, t / 120.0, "ok", "hlm"], f[:5]
            assert np.frombuffer(fill["/lacuna/filled"][2], np.uint8)[miss].all()
            p = fill["/lacuna/positions"]
            assert p[:2] == ["osc-pos", t] and len(p) == 2 + 3 * len(kin.joints)
            got.append(np.reshape(p[2:], (-1, 3)))
            done.append(f[7:])
        want = kin.positions(np.array(done, np.float64))
        np.testing.assert_allclose(np.array(got), want, atol=1e-5, rtol=0)
        assert np.ptp(np.array(got)[:, kin.joints.index("lhand")], axis=0).max() > 0.01  # the filled arm moved
        # a plain OSC hello on the same stream: no joints in the ack, no positions in the fills
        u.sendto(_osc_msg("/lacuna/hello", [("osc-pos", "s"), ("", "s")] + [(c, "s") for c in take.channels]),
                 (host, int(port)))
        assert set(_osc_parts(u.recv(65536))) == {"/lacuna/hello-ack"}
        u.sendto(_osc_msg("/lacuna/frame", [("osc-pos", "s"), (99, "i"), (1.0, "d")] + [(float(v), "f") for v in sent[0]]),
                 (host, int(port)))
        fill = _osc_parts(u.recv(65536))
        assert "/lacuna/fill" in fill and "/lacuna/positions" not in fill
        # a model without a skeleton: the OSC hello asking for positions is refused no_skeleton
        u.sendto(_osc_msg("/lacuna/hello/positions", [("osc-held", "s"), ("hold", "s")] + [(c, "s") for c in take.channels]),
                 (host, int(port)))
        err = _osc_parts(u.recv(65536))
        assert err["/lacuna/error"][0] == "no_skeleton", err
    finally:
        u.close()
