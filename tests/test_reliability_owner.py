"""Issue 18, F3: a stream belongs to whoever opened it.  Real daemon, real ZeroMQ/OSC sockets.

Before, one frame with seq 10^9 from another client made every later frame of the victim
`late` (and the forged values went out on PUB as the victim's fill); anyone could `hello` it to
another model or `reset` it, over ZeroMQ or OSC, between CURVE clients too.  Now: frames, hello
and reset from another principal are refused `not_owner` and counted (`foreign` on the stream);
reload and resetting others need an operator; the owner reconnecting takes its stream back with
its claim token; a client that meets a `late` it did not cause restarts its stream.
"""
from __future__ import annotations

import shutil
import socket

import fuzzgen
import numpy as np
import pytest
import zmq
from reliability_daemon import Daemon, LockStep, Sockets, control, recv_msg, status, write_config
from test_reliability_access import curve_dealer, lacuna
from test_reliability_faults import all_filled

from clients.client import Client
from daemon import wire
from mocap.baselines import HoldModel
from mocap.datasets import load_trial


@pytest.fixture(scope="module")
def walk(data):
    m = load_trial("35_01")
    f = m.frames.astype(np.float32)
    f[::6, 30:33] = np.nan
    return f, list(m.channels), HoldModel.fit([m.frames], list(m.channels))


def _osc_answer(u: socket.socket) -> bytes:
    u.settimeout(5)
    return u.recv(65535)


def test_another_connection_cannot_touch_a_stream(tmp_path, walk):
    frames, channels, model = walk
    model.save(str(tmp_path / "walk.npz"))
    ep = write_config(tmp_path / "lacuna.toml", {"walk": {"file": "walk.npz"}, "floor": {"builtin": "passthrough"}},
                      osc=True)
    d = Daemon(tmp_path / "lacuna.toml", tmp_path / "daemon.log").start()
    S = Sockets()
    sub = S.make(zmq.SUB, ep["pub"])
    sub.setsockopt(zmq.SUBSCRIBE, b"victim")
    victim = LockStep(ep["router"], "victim", frames, hello=channels)
    u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    u.bind(("127.0.0.1", 0))
    try:
        victim.start()
        while len(victim.answers) < 20:
            assert victim.is_alive(), victim.problems
            victim.join(0.01)
        att = S.make(zmq.DEALER, ep["router"])
        forged = wire.Frame("victim", 10**9, 0.0, np.full(len(channels), 1e6, np.float32))
        attempts = [wire.encode(forged),
                    wire.encode(wire.Hello("victim", channels, "floor")),
                    wire.encode(wire.Bundle([forged]))]
        for data in attempts:
            att.send(data)
            m = recv_msg(att)
            m = m.items[0] if isinstance(m, wire.Replies) else m
            assert isinstance(m, wire.ErrorMsg) and m.reason == "not_owner", m
        # over OSC: a frame and a reset of the ZeroMQ stream
        u.sendto(fuzzgen.osc_frame("victim", 10**9, 0.0, frames[0]), ep["osc"])
        assert b"not_owner" in _osc_answer(u)
        u.sendto(fuzzgen.osc_message("/lacuna/reset", [("s", "victim")]), ep["osc"])
        assert b"not_owner" in _osc_answer(u)
        # an OSC stream is its source address's: another port cannot feed it
        u.sendto(fuzzgen.osc_frame("oscs", 0, 0.0, frames[0]), ep["osc"])
        assert b"/lacuna/fill" in _osc_answer(u)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u2:
            u2.bind(("127.0.0.1", 0))
            u2.sendto(fuzzgen.osc_frame("oscs", 5, 0.0, frames[0]), ep["osc"])
            assert b"not_owner" in _osc_answer(u2)
        n0 = len(victim.answers)
        while len(victim.answers) < n0 + 20:
            assert victim.is_alive(), victim.problems
            victim.join(0.01)
        victim.finish()
        all_filled(victim, "walk")  # never `late`, never another model
        st = status(S, ep["router"])
        v = st["streams"]["victim"]
        assert v["foreign"] == 5 and v["rejected"] == 0 and v["dropped"] == 0
        assert st["streams"]["oscs"]["foreign"] == 1
        assert st["rejected"]["not_owner"] == 6
        published = []
        while sub.poll(200):
            topic, body = sub.recv_multipart()
            published.append(wire.decode(body))
        assert published and all(m.seq < 10**9 and m.model == "walk" for m in published if isinstance(m, wire.FillMsg))
        assert d.alive()
    finally:
        victim.stop_flag.set()
        u.close()
        S.close()
        d.stop()


def test_the_owner_takes_its_stream_back_after_a_reconnect(tmp_path, walk):
    """The client library reconnects with a new ZeroMQ identity: its hello's claim token takes
    the stream over; a frame-only client that lost its identity resets and goes on; a stranger
    without the token gets the stream once its owner released it (closed) or, after a crash,
    fell silent for idle_timeout_s."""
    frames, channels, model = walk
    model.save(str(tmp_path / "walk.npz"))
    ep = write_config(tmp_path / "lacuna.toml", {"walk": {"file": "walk.npz"}}, daemon={"idle_timeout_s": 1.0})
    d = Daemon(tmp_path / "lacuna.toml", tmp_path / "daemon.log").start()
    S = Sockets()
    try:
        with Client(ep["router"], "recon", channels) as c:
            out = [c.fill(frames[i]) for i in range(30)]
            c.reconnect()
            out += [c.fill(frames[i]) for i in range(30, 60)]
            assert all(isinstance(m, wire.FillMsg) for m in out), [m for m in out if not isinstance(m, wire.FillMsg)][:2]
            stranger = S.make(zmq.DEALER, ep["router"])
            stranger.send(wire.encode(wire.Hello("recon", channels)))
            m = recv_msg(stranger)
            assert isinstance(m, wire.ErrorMsg) and m.reason == "not_owner"
        with Client(ep["router"], "anon") as a:  # no channel list: no hello, no claim
            assert all(isinstance(a.fill(frames[i]), wire.FillMsg) for i in range(10))
        with Client(ep["router"], "anon") as b:  # (a restarted plugin: new identity, seq from 0)
            assert isinstance(b.fill(frames[0]), wire.FillMsg) and b.session.resyncs == 1
        st = status(S, ep["router"])
        assert st["streams"]["recon"]["frames_out"] == 60 and st["takeovers"] >= 1
        # the client closed cleanly and released "recon": anyone may open it now
        stranger.send(wire.encode(wire.Hello("recon", channels)))
        assert isinstance(recv_msg(stranger), wire.HelloAck)
        # a client that crashed (socket gone, nothing released): free once silent for idle_timeout_s
        crash = Client(ep["router"], "crash", channels)
        assert isinstance(crash.fill(frames[0]), wire.FillMsg)
        crash._close_socket()
        stranger.send(wire.encode(wire.Hello("crash", channels)))
        m = recv_msg(stranger)
        assert isinstance(m, wire.ErrorMsg) and m.reason == "not_owner"
        d.wait_for("stream_expired", 10, stream="crash")
        stranger.send(wire.encode(wire.Hello("crash", channels)))
        assert isinstance(recv_msg(stranger), wire.HelloAck)
        crash.close()
        assert d.alive()
    finally:
        S.close()
        d.stop()


@pytest.fixture
def curve_keys(tmp_path):
    kd = tmp_path / "keys"
    for name in ("server", "studio", "op"):
        r = lacuna("keys", str(kd), "--name", name)
        assert r.returncode == 0, r.stderr
    auth, ops = tmp_path / "authorized", tmp_path / "operators"
    auth.mkdir()
    ops.mkdir()
    for name in ("studio", "op"):
        shutil.copy(kd / f"{name}.key", auth / f"{name}.key")
    shutil.copy(kd / "op.key", ops / "op.key")
    return kd, auth, ops


def test_curve_key_owns_streams_and_only_operators_reload_or_reset_others(tmp_path, curve_keys):
    kd, auth, ops = curve_keys
    extra = (f'[security]\nserver_secret_key = "{kd / "server.key_secret"}"\nauthorized_keys = "{auth}"\n'
             f'operator_keys = "{ops}"\n')
    ep = write_config(tmp_path / "lacuna.toml", {"floor": {"builtin": "passthrough"}}, extra=extra)
    d = Daemon(tmp_path / "lacuna.toml", tmp_path / "daemon.log").start()
    S = Sockets()
    x = np.array([1.0, np.nan, 3.0], np.float32)
    studio = (str(kd / "studio.key_secret"), str(kd / "server.key"))
    try:
        with Client(ep["router"], "s1", curve=studio) as c:
            assert all(isinstance(c.fill(x), wire.FillMsg) for _ in range(50))
        # the same key, a new process counting from 0: `late`, which this client did not cause
        with Client(ep["router"], "s1", curve=studio) as c2:
            m = c2.fill(x)
            assert isinstance(m, wire.FillMsg) and m.seq == 0 and c2.session.resyncs == 1
        st_ = curve_dealer(S, ep["router"], kd, "studio")
        op = curve_dealer(S, ep["router"], kd, "op")
        op.send(wire.encode(wire.Frame("o1", 0, 0.0, x)))
        assert isinstance(recv_msg(op), wire.FillMsg)
        st_.send(wire.encode(wire.Frame("o1", 1, 0.0, x)))  # another key's stream
        m = recv_msg(st_)
        assert isinstance(m, wire.ErrorMsg) and m.reason == "not_owner"
        st_.send(wire.encode(wire.Control("reset", "o1")))
        m = recv_msg(st_)
        assert isinstance(m, wire.ErrorMsg) and m.reason == "not_owner"
        st_.send(wire.encode(wire.Control("reload")))
        m = recv_msg(st_)
        assert isinstance(m, wire.ErrorMsg) and m.reason == "not_operator"
        assert control(op, "reset", "s1")["stream"] == "s1"  # an operator resets anyone's stream
        assert control(op, "reload", timeout_ms=15_000)["_ok"] is True
        info = control(op, "status")
        assert "s1" not in info["streams"] and info["streams"]["o1"]["foreign"] == 2
        assert info["rejected"] == {"not_owner": 2, "not_operator": 1}
        assert info["security"]["operator_keys"] == 1
        assert d.alive()
    finally:
        S.close()
        d.stop()
