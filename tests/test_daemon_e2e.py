"""The daemon as a separate process on real loopback sockets (ZeroMQ, OSC, HTTP, unix datagram).

Every test starts `python -m lacuna.cli serve --config ...` with ``tcp://127.0.0.1:*`` endpoints
(the daemon reports the ports it bound in its ready log line), talks to it with real sockets
(linger 0, receives with timeouts) and kills it in teardown.
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request

import numpy as np
import pytest
import zmq
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_message import OscMessage
from pythonosc.osc_message_builder import OscMessageBuilder
from waiting import wait_until

from clients import loadgen
from clients.configfile import write_config as write_toml
from clients.control import control
from clients.harness import DaemonProcess
from daemon import wire
from mocap.baselines import HoldModel, NearestNeighbourModel

RECV_MS = 5000
CH = ["lfemur.rx", "lfemur.ry", "lfemur.rz", "ltibia.rx", "rfemur.rx", "rfemur.ry", "rfemur.rz", "rtibia.rx"]


def hold_file(path, mean_value: float, channels=CH):
    C = len(channels)
    HoldModel(channels, np.full(C, mean_value), np.full(C, 2.0)).save(str(path))
    return str(path)


def write_config(tmp_path, models: dict[str, dict], *, default=None, osc=False, http=False, pull=False,
                 budget_ms=250.0, overdue=None, realtime=None, extra="") -> str:
    # (a generous budget by default: with overdue = "drop" a frame a stall of the test machine holds
    # past the budget is answered `overdue`; the tests about the budget set their own)
    d: dict = {"budget_ms": budget_ms, "idle_timeout_s": 60, "max_gap_frames": 5}
    d.update({k: v for k, v in (("overdue", overdue), ("realtime_priority", realtime), ("default_model", default)) if v})
    cfg = {"daemon": d, **{f"models.{name}": spec for name, spec in models.items()},
           "zmq": {"router": "tcp://127.0.0.1:*", "pub": "tcp://127.0.0.1:*", **({"pull": "tcp://127.0.0.1:*"} if pull else {})}}
    if osc:
        cfg["osc"] = {"listen": "127.0.0.1:0"}
    if http:
        cfg["metrics"] = {"http": "127.0.0.1:0"}
    return write_toml(tmp_path / "lacuna.toml", cfg, extra)


@pytest.fixture
def ctx():
    c = zmq.Context()
    socks: list[zmq.Socket] = []

    def make(kind):
        s = c.socket(kind)
        s.setsockopt(zmq.LINGER, 0)
        socks.append(s)
        return s

    yield make
    for s in socks:
        s.close(0)
    c.term()


@pytest.fixture
def daemons():
    procs: list[DaemonProcess] = []

    def start(config, env=None):
        d = DaemonProcess(config, env=env)
        procs.append(d)
        return d.start()

    yield start
    for d in procs:
        if d.proc is not None and d.proc.poll() is None:
            d.proc.kill()
            d.proc.wait(10)


def recv(sock, timeout_ms=RECV_MS):
    if not sock.poll(timeout_ms):
        raise TimeoutError("no answer from the daemon")
    return wire.decode(sock.recv_multipart()[-1], 64 << 20)


def dealer(ctx, d):
    s = ctx(zmq.DEALER)
    s.connect(d.endpoints["router"])
    return s


def frame(sid, seq, values, observed=None):
    return wire.encode(wire.Frame(sid, seq, seq / 120.0, np.asarray(values, np.float32), observed))


# ---- request/reply ------------------------------------------------------------------------------
def test_req_reply_round_trip_with_req_socket_passthrough(tmp_path, daemons, ctx):
    d = daemons(write_config(tmp_path, {"floor": {"builtin": "passthrough"}}))
    s = ctx(zmq.REQ)  # REQ adds the empty delimiter frame: the reply must keep the envelope
    s.connect(d.endpoints["router"])
    vals = np.array([1.5, np.nan, -3.25], np.float32)
    s.send(frame("a", 0, vals))
    m = recv(s)
    assert isinstance(m, wire.FillMsg) and m.status == "passthrough" and m.model == "floor"
    assert m.angles[0] == 1.5 and np.isnan(m.angles[1]) and m.angles[2] == -3.25
    assert not m.filled.any() and m.proc_us >= 0 and (m.stream, m.seq, m.t) == ("a", 0, 0.0)


def test_handshake_maps_studio_channels_onto_model(tmp_path, daemons, ctx):
    model = hold_file(tmp_path / "hold.npz", 7.0)
    d = daemons(write_config(tmp_path, {"walk": {"file": model}}))
    s = dealer(ctx, d)
    # the studio sends two model channels in its own order, one channel the model lacks, and
    # omits the other six model channels
    studio = ["rfemur.rx", "studio.prop", "lfemur.rx"]
    s.send(wire.encode(wire.Hello("p1", studio)))
    ack = recv(s)
    assert isinstance(ack, wire.HelloAck) and ack.model == "walk"
    assert ack.passthrough == ["studio.prop"]
    assert sorted(ack.missing) == sorted(set(CH) - {"rfemur.rx", "lfemur.rx"})
    s.send(frame("p1", 0, [11.0, 99.0, np.nan]))  # lfemur.rx missing: hold fills it with the mean
    m = recv(s)
    assert m.status == "ok"
    assert m.angles.tolist() == [11.0, 99.0, 7.0]
    assert m.filled.tolist() == [False, False, True]
    assert m.std.tolist() == [0.0, 0.0, 2.0]
    s.send(frame("p1", 1, [np.nan, np.nan, 5.0]))  # the pass-through channel stays missing, unfilled
    m = recv(s)
    assert m.angles[0] == 11.0 and np.isnan(m.angles[1]) and m.angles[2] == 5.0
    assert m.filled.tolist() == [True, False, False]
    # a stream without handshake uses the model's own channels
    s.send(frame("p2", 0, np.arange(len(CH), dtype=float)))
    assert recv(s).angles.tolist() == list(range(len(CH)))
    s.send(frame("p2", 1, [1.0, 2.0]))  # wrong width: rejected with a reason, stream still served
    e = recv(s)
    assert isinstance(e, wire.ErrorMsg) and e.reason == "width" and "8 channels" in e.detail
    s.send(wire.encode(wire.Hello("p3", ["nothing.matches"])))
    e = recv(s)
    assert isinstance(e, wire.ErrorMsg) and e.reason == "bad_channels"
    s.send(wire.encode(wire.Hello("p4", CH[:2], "nosuchmodel")))
    e = recv(s)
    assert isinstance(e, wire.ErrorMsg) and e.reason == "unknown_model"


def test_sequence_gaps_become_predictions_and_late_duplicates_are_dropped(tmp_path, daemons, ctx):
    d = daemons(write_config(tmp_path, {"walk": {"file": hold_file(tmp_path / "h.npz", 0.0)}}))
    s = dealer(ctx, d)
    row = np.arange(len(CH), dtype=float)
    answers = []
    for seq in (0, 1, 4, 3, 4, 2, 5, 100):
        s.send(frame("g", seq, row))
        answers.append(recv(s))
    kinds = [(type(a).__name__, a.seq, getattr(a, "reason", None), getattr(a, "gap", None)) for a in answers]
    assert kinds == [("FillMsg", 0, None, 0), ("FillMsg", 1, None, 0), ("FillMsg", 4, None, 2),
                     ("Drop", 3, "late", None), ("Drop", 4, "duplicate", None), ("Drop", 2, "late", None),
                     ("FillMsg", 5, None, 0), ("FillMsg", 100, None, 94)]
    s.send(wire.encode(wire.Control("status")))
    st = recv(s).result["streams"]["g"]
    # 2 predictions for seq 2..3; the gap of 94 exceeds max_gap_frames = 5: a restart, no predictions
    assert (st["predicted"], st["restarts"], st["dropped_late"], st["dropped_duplicate"]) == (2, 1, 2, 1)
    assert (st["frames_in"], st["frames_out"], st["last_seq"]) == (8, 5, 100)


def test_many_streams_at_once_all_answered_and_counts_agree(tmp_path, daemons):
    d = daemons(write_config(tmp_path, {"walk": {"file": hold_file(tmp_path / "h.npz", 1.0)}}))
    rng = np.random.default_rng(0)
    miss = np.zeros(len(CH), bool)
    miss[[1, 5]] = True
    frames = loadgen.make_frames(240, len(CH), miss, rng)
    res = loadgen.run_load(d.endpoints["router"], None, frames, n_streams=48, rate=60.0, seconds=1.0, progress=False)
    assert res.lost == 0 and res.errors == 0
    assert res.served + res.dropped == res.sent == 48 * 60
    st = loadgen_status(d)
    assert st["counters"]["frames_in"] == res.sent
    assert st["counters"]["frames_out"] == res.served
    assert len(st["streams"]) == 48
    assert all(v["frames_in"] == 60 for v in st["streams"].values())


def loadgen_status(d):
    rep = control(d.endpoints["router"], "status", timeout_s=5.0)
    assert rep.ok
    return rep.result


# ---- PUSH -> PUB ------------------------------------------------------------------------------
def test_push_to_pub_round_trip(tmp_path, daemons, ctx):
    d = daemons(write_config(tmp_path, {"walk": {"file": hold_file(tmp_path / "h.npz", 3.0)}}, pull=True))
    sub = ctx(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"cam")
    sub.connect(d.endpoints["pub"])
    push = ctx(zmq.PUSH)
    push.connect(d.endpoints["pull"])
    row = np.arange(len(CH), dtype=np.float32)
    row[2] = np.nan
    # PUB/SUB: a subscription takes a moment to reach the publisher (slow joiner); joined once a
    # first fill comes through (on a stream of its own, "cam0", which the test then leaves alone)
    joins = iter(range(10**6))
    wait_until(lambda: push.send(frame("cam0", next(joins), row)) or sub.poll(50), 10, "a first published fill")
    while sub.poll(200):  # (the join's other fills)
        assert sub.recv_multipart()[0] == b"cam0"

    def next_msg():
        if not sub.poll(RECV_MS):
            raise TimeoutError("nothing published")
        topic, body = sub.recv_multipart()
        return topic, wire.decode(body)

    # paced: each frame is served before the next arrives
    for seq in range(5):
        push.send(frame("cam1", seq, row))
        topic, m = next_msg()
        assert topic == b"cam1" and isinstance(m, wire.FillMsg) and m.seq == seq
        assert m.angles[2] == 3.0 and m.filled[2] and m.filled.sum() == 1
    # a burst: the daemon serves the newest; every older frame is answered as conflated (or
    # served, if the daemon got to it first): each seq exactly once, the last one filled (the
    # drops of a burst can come after the fill that superseded them)
    for seq in range(5, 45):
        push.send(frame("cam1", seq, row))
    seen = {}
    while len(seen) < 40:
        topic, m = next_msg()
        assert topic == b"cam1" and m.seq not in seen
        seen[m.seq] = m
    assert sorted(seen) == list(range(5, 45)) and isinstance(seen[44], wire.FillMsg)
    assert all(isinstance(m, wire.FillMsg) or m.reason == "conflated" for m in seen.values())


def test_a_burst_is_answered_frame_by_frame_with_its_superseded_frames_after_the_fill(tmp_path, daemons, ctx):
    """The daemon stopped (SIGSTOP) while a client sends a burst, so it reads the burst at once:
    the newest frame is served, every other frame gets the answer it would have had one by one
    (conflated, duplicate, or an error for a malformed one), and the counters agree."""
    d = daemons(write_config(tmp_path, {"walk": {"file": hold_file(tmp_path / "h.npz", 3.0)}}))
    s = dealer(ctx, d)
    row = np.arange(len(CH), dtype=np.float32)
    row[2] = np.nan
    s.send(frame("take", 0, row))  # opens the stream
    assert isinstance(recv(s), wire.FillMsg)
    expect: dict[int, list[str]] = {}  # seq -> the answers its frames must get
    burst = []
    for seq in range(1, 121):
        if seq % 37 == 0:  # infinity where a value is promised: an error, not a frame
            bad = row.copy()
            bad[0] = np.inf
            burst.append(frame("take", seq, bad))
            expect[seq] = ["error:non_finite"]
            continue
        if seq % 29 == 0:  # a wrong channel count
            burst.append(frame("take", seq, row[:-1]))
            expect[seq] = ["error:width"]
            continue
        burst.append(frame("take", seq, row))
        expect[seq] = ["conflated"]
        if seq % 20 == 0:  # sent twice
            burst.append(frame("take", seq, row))
            expect[seq].append("duplicate")
    expect[120] = ["duplicate", "fill"]
    os.kill(d.proc.pid, signal.SIGSTOP)
    try:
        for b in burst:
            s.send(b)
        # (the stopped daemon can signal nothing: this gives loopback time to move the burst into
        # its socket while it is stopped; a piece that arrives after SIGCONT is allowed for below)
        time.sleep(0.3)
    finally:
        os.kill(d.proc.pid, signal.SIGCONT)
    got: dict[int, list[str]] = {}
    order = []
    for _ in range(len(burst)):
        m = recv(s)
        got.setdefault(m.seq, []).append("fill" if isinstance(m, wire.FillMsg) else m.reason
                                         if isinstance(m, wire.Drop) else f"error:{m.reason}")
        order.append((m.seq, got[m.seq][-1]))
    # ZeroMQ's I/O thread, woken with the daemon, can hand the burst over in more than one piece:
    # the newest frame of an earlier piece is then served (in-order handling gives the same)
    split = {k for k, v in got.items() if k != 120 and "fill" in v}
    assert len(split) <= 10, f"the burst came in {len(split) + 1} pieces: the set-aside path was barely used"
    for k in split:
        expect[k] = ["fill" if a == "conflated" else a for a in expect[k]]
    assert {k: sorted(v) for k, v in got.items()} == {k: sorted(v) for k, v in expect.items()}
    # the fill of the newest frame went out before the answers to the frames it superseded
    last = max(k for k, v in got.items() if "conflated" in v)
    assert order.index((120, "fill")) < order.index((last, "conflated"))
    st = loadgen_status(d)["streams"]["take"]
    n_err = 3 + 4
    assert st["frames_out"] == 2 + len(split) and st["dropped_duplicate"] == 6 and st["rejected"] == n_err
    assert st["dropped_conflated"] == 119 - n_err - len(split)
    assert st["frames_in"] == 1 + len(burst) - n_err  # (a refused frame is not taken in)
    assert not s.poll(200)  # nothing answered twice


def test_frames_it_cannot_answer_within_budget_are_dropped_overdue_until_a_reload_says_serve(tmp_path, daemons, ctx):
    """A budget no frame can meet (0.05 ms: holding one stream and sending its answer cost more):
    every frame is answered `drop` / `overdue` and counted, nothing waits, a repeat is a
    duplicate; a SIGHUP with overdue = "serve" fills the next frames (late, counted over budget)."""
    model = hold_file(tmp_path / "h.npz", 3.0)
    cfg = write_config(tmp_path, {"walk": {"file": model}}, budget_ms=0.05)
    d = daemons(cfg)
    s = dealer(ctx, d)
    row = np.arange(len(CH), dtype=np.float32)
    row[2] = np.nan
    for seq in range(5):
        s.send(frame("tight", seq, row))
        m = recv(s)
        assert isinstance(m, wire.Drop) and (m.seq, m.reason) == (seq, "overdue")
    s.send(frame("tight", 4, row))
    m = recv(s)
    assert isinstance(m, wire.Drop) and (m.seq, m.reason) == (4, "duplicate")
    st = loadgen_status(d)
    assert st["overdue"] == "drop"
    t = st["streams"]["tight"]
    assert t["dropped_overdue"] == 5 and t["dropped_duplicate"] == 1 and t["frames_out"] == 0 and t["dropped"] == 6
    assert st["counters"]["dropped_overdue"] == 5
    write_config(tmp_path, {"walk": {"file": model}}, budget_ms=0.05, overdue="serve")
    d.signal(signal.SIGHUP)
    assert d.wait_for("reload_done", 30)["ok"] is True
    for seq in range(5, 8):
        s.send(frame("tight", seq, row))
        m = recv(s)
        assert isinstance(m, wire.FillMsg) and m.seq == seq and m.filled[2] and m.angles[2] == 3.0
    st = loadgen_status(d)
    t = st["streams"]["tight"]
    assert st["overdue"] == "serve" and t["frames_out"] == 3 and t["over_budget"] == 3 and t["dropped_overdue"] == 5


def _policy(pid: int, tid: int) -> tuple[int, int]:
    return os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority


def test_realtime_priority_goes_to_the_serving_and_zeromq_io_threads_only(tmp_path, daemons, ctx):
    """daemon.realtime_priority: the serving thread and ZeroMQ's I/O threads run SCHED_RR at that
    priority (read back from the kernel), every other thread of the daemon (ZeroMQ's reaper, the
    log reader) stays ordinary, and a reload keeps it (the reload thread's own reset is tested in
    tests/test_daemon_units.py).  Where the process may not (no
    CAP_SYS_NICE nor RLIMIT_RTPRIO), `status` says why and the daemon serves on."""
    d = daemons(write_config(tmp_path, {"walk": {"file": hold_file(tmp_path / "h.npz", 3.0)}}, realtime=3))
    s = dealer(ctx, d)
    row = np.arange(len(CH), dtype=np.float32)
    row[2] = np.nan
    s.send(frame("rt", 0, row))
    assert isinstance(recv(s), wire.FillMsg)
    st = loadgen_status(d)
    rt = st["realtime"]
    assert rt["requested_priority"] == 3
    pid = d.proc.pid
    if not rt["held"]:
        assert "SCHED_RR" in rt["error"] and st["counters"]["realtime_refused"] == 1
        assert _policy(pid, pid) == (os.SCHED_OTHER, 0)
        return

    def threads() -> dict[int, str]:
        out = {}
        for t in os.listdir(f"/proc/{pid}/task"):
            try:
                with open(f"/proc/{pid}/task/{t}/comm") as f:
                    out[int(t)] = f.read().strip()
            except FileNotFoundError:  # a thread that ended meanwhile
                pass
        return out

    def check() -> None:
        names = threads()
        io = [t for t, n in names.items() if n.startswith("ZMQbg/IO")]
        assert io and rt["error"] is None
        for t, n in names.items():
            want = (os.SCHED_RR, 3) if t == pid or t in io else (os.SCHED_OTHER, 0)
            try:
                got = _policy(pid, t)
            except ProcessLookupError:  # ended meanwhile
                continue
            assert got == want, (t, n)

    check()
    assert sorted(rt["threads"].values()) == ["rr"] * (1 + len([n for n in threads().values() if n.startswith("ZMQbg/IO")]))
    d.signal(signal.SIGHUP)
    assert d.wait_for("reload_done", 30)["ok"] is True
    rt = loadgen_status(d)["realtime"]
    assert rt["held"]
    check()
    s.send(frame("rt", 1, row))
    assert isinstance(recv(s), wire.FillMsg)


def test_a_realtime_request_the_process_may_not_make_is_reported_and_it_serves_on(tmp_path, ctx):
    """Started without the right to real-time scheduling (RLIMIT_RTPRIO 0 and, as root, no
    CAP_SYS_NICE: a wrapper drops both before exec), the daemon logs why, counts it, shows it in
    `status`, and serves at the ordinary priority."""
    wrapper = tmp_path / "python-without-rt"
    wrapper.write_text(f"""#!{sys.executable}
import ctypes, os, resource, sys
resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
if os.geteuid() == 0:  # PR_CAPBSET_DROP (24) CAP_SYS_NICE (23): gone from root after the exec below
    if ctypes.CDLL(None, use_errno=True).prctl(24, 23, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP, CAP_SYS_NICE)")
os.execv(sys.executable, [sys.executable, *sys.argv[1:]])
""")
    wrapper.chmod(0o755)
    d = DaemonProcess(write_config(tmp_path, {"walk": {"file": hold_file(tmp_path / "h.npz", 3.0)}}, realtime=3),
                      python=str(wrapper))
    try:
        d.start()
        refused = d.wait_for("realtime_refused", 10)
        assert refused["priority"] == 3 and "not permitted" in refused["error"]
        s = dealer(ctx, d)
        row = np.arange(len(CH), dtype=np.float32)
        row[2] = np.nan
        s.send(frame("rt", 0, row))
        m = recv(s)
        assert isinstance(m, wire.FillMsg) and m.angles[2] == 3.0
        st = loadgen_status(d)
        rt = st["realtime"]
        assert not rt["held"] and rt["threads"] == {} and "SCHED_RR" in rt["error"] and rt["requested_priority"] == 3
        assert st["counters"]["realtime_refused"] == 1
        assert all(_policy(d.proc.pid, int(t)) == (os.SCHED_OTHER, 0) for t in os.listdir(f"/proc/{d.proc.pid}/task"))
    finally:
        d.stop()


# ---- OSC --------------------------------------------------------------------------------------
def _osc_frame(sid, seq, values):
    b = OscMessageBuilder("/lacuna/frame")
    b.add_arg(sid, "s")
    b.add_arg(seq, "i")
    b.add_arg(seq / 120.0, "d")
    for v in values:
        b.add_arg(float(v), "f")
    return b.build().dgram


def test_osc_round_trip(tmp_path, daemons):
    d = daemons(write_config(tmp_path, {"walk": {"file": hold_file(tmp_path / "h.npz", -4.0)}}, osc=True))
    host, port = d.endpoints["osc"].rsplit(":", 1)
    u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    u.bind(("127.0.0.1", 0))
    u.settimeout(5.0)
    try:
        b = OscMessageBuilder("/lacuna/hello")
        for a in ["osc1", "", "lfemur.ry", "lfemur.rx", "extra.z"]:
            b.add_arg(a, "s")
        u.sendto(b.build().dgram, (host, int(port)))
        ack = OscMessage(u.recv(65535))
        assert ack.address == "/lacuna/hello-ack" and ack.params == ["osc1", "walk", 3, 1, 6]
        u.sendto(_osc_frame("osc1", 0, [1.0, float("nan"), 2.5]), (host, int(port)))
        bundle = OscBundle(u.recv(65535))
        msgs = {m.address: m.params for m in bundle}
        fill = msgs["/lacuna/fill"]
        assert fill[:7] == ["osc1", 0, 0.0, "ok", "walk", fill[5], 0]
        assert fill[7:] == [1.0, -4.0, 2.5]
        assert msgs["/lacuna/std"][2:] == [0.0, 2.0, 0.0]
        assert msgs["/lacuna/filled"][2] == b"\x00\x01\x00"
        u.sendto(b"not osc at all", (host, int(port)))
        err = OscMessage(u.recv(65535))
        assert err.address == "/lacuna/error" and err.params[0] == "not_osc"
    finally:
        u.close()


def test_osc_bundle_of_performers_is_served_message_by_message(tmp_path, daemons):
    """A capture tool sends each instant as one OSC bundle (python-osc's builder, timetag
    "immediately"): a hello and frames of several performers, one of them malformed. Each
    message is answered as if it had come alone; the malformed one costs only itself."""
    from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder

    d = daemons(write_config(tmp_path, {"walk": {"file": hold_file(tmp_path / "h.npz", -4.0)}}, osc=True))
    host, port = d.endpoints["osc"].rsplit(":", 1)
    u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    u.bind(("127.0.0.1", 0))
    u.settimeout(5.0)
    row = [1.0, float("nan"), 2.5, 0.0, 1.0, 2.0, 3.0, 4.0]
    try:
        bb = OscBundleBuilder(IMMEDIATELY)
        h = OscMessageBuilder("/lacuna/hello")
        for a in ["actor3", "", "lfemur.ry", "lfemur.rx"]:
            h.add_arg(a, "s")
        bb.add_content(h.build())
        bb.add_content(OscMessage(_osc_frame("actor1", 0, row)))
        bb.add_content(OscMessage(_osc_frame("actor2", 0, row[:-1] + [float("inf")])))  # infinity: refused
        bb.add_content(OscMessage(_osc_frame("actor2", 1, row)))
        bb.add_content(OscMessage(_osc_frame("actor3", 0, [5.0, float("nan")])))
        u.sendto(bb.build().dgram, (host, int(port)))
        fills, other = {}, []
        while len(fills) + len(other) < 5:
            data = u.recv(65535)
            if OscBundle.dgram_is_bundle(data):
                msgs = {m.address: m.params for m in OscBundle(data)}
                fills[msgs["/lacuna/fill"][0]] = msgs["/lacuna/fill"]
            else:
                m = OscMessage(data)
                other.append((m.address, m.params[0]))
        assert sorted(other) == [("/lacuna/error", "non_finite"), ("/lacuna/hello-ack", "actor3")]
        assert sorted(fills) == ["actor1", "actor2", "actor3"]
        assert fills["actor1"][7:] == [1.0, -4.0, 2.5, 0.0, 1.0, 2.0, 3.0, 4.0]
        assert fills["actor2"][1] == 1 and fills["actor3"][7:] == [5.0, -4.0]  # (its own channel order)
        st = loadgen_status(d)
        assert st["counters"]["osc_bundles_in"] == 1 and st["counters"]["messages_in"] == 2  # it, and this status request
        # (actor2's refused frame came before its stream existed: counted globally only)
        assert st["rejected"] == {"non_finite": 1} and st["streams"]["actor2"]["frames_out"] == 1
    finally:
        u.close()


# ---- bad input ----------------------------------------------------------------------------------
def test_bad_messages_are_counted_rejections_and_other_streams_keep_going(tmp_path, daemons, ctx):
    d = daemons(write_config(tmp_path, {"floor": {"builtin": "passthrough"}}, http=True))
    good, bad = dealer(ctx, d), dealer(ctx, d)
    bads = [b"", b"\xc1", b"\x81\xa1v\x02", wire.encode(wire.Frame("x", 0, 0.0, np.ones(2, np.float32)))[:-1],
            b"\x00" * 70000]
    for i, data in enumerate(bads):
        bad.send(data)
        good.send(frame("good", i, [1.0, 2.0]))
        e = recv(bad)
        assert isinstance(e, wire.ErrorMsg), e
        assert isinstance(recv(good), wire.FillMsg)
    st = loadgen_status(d)
    assert st["counters"]["rejected"] == len(bads)
    assert st["rejected"] == {"not_msgpack": 3, "version": 1, "too_large": 1}
    assert st["streams"]["good"]["frames_out"] == len(bads)
    port = d.endpoints["metrics_http"].rsplit(":", 1)[1]

    def scrape() -> str:  # the exposition snapshot refreshes every housekeeping tick (0.5 s)
        text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
        return text if "lacuna_frames_out_total 5" in text else ""

    text = wait_until(scrape, 10, "a metrics snapshot after the 5 frames", 0.1)
    assert 'lacuna_rejected_by_reason_total{reason="not_msgpack"} 3' in text
    assert "lacuna_frames_out_total 5" in text
    assert 'lacuna_stream_frames_out_total{stream="good",model="floor"} 5' in text


def test_control_reset_list_models_and_status_cli(tmp_path, daemons, ctx):
    d = daemons(write_config(tmp_path, {"floor": {"builtin": "passthrough"},
                                        "walk": {"file": hold_file(tmp_path / "h.npz", 0.0)}}, default="walk"))
    s = dealer(ctx, d)
    s.send(frame("r", 0, np.zeros(len(CH))))
    recv(s)
    s.send(wire.encode(wire.Control("list-models")))
    lm = recv(s)
    assert lm.ok and set(lm.result["models"]) == {"floor", "walk"} and lm.result["default"] == "walk"
    out = subprocess.run([sys.executable, "-m", "lacuna.cli", "status", "--connect", d.endpoints["router"]],
                         capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    assert "walk" in out.stdout and "r " in out.stdout and "p99" in out.stdout
    s.send(wire.encode(wire.Control("reset", "r")))
    assert recv(s).ok
    s.send(frame("r", 0, np.zeros(len(CH))))  # after a reset seq 0 is new again, not late
    assert isinstance(recv(s), wire.FillMsg)
    s.send(wire.encode(wire.Control("reset", "nobody")))
    r = recv(s)
    assert not r.ok and "nobody" in r.error


# ---- reload -------------------------------------------------------------------------------------
class Sender(threading.Thread):
    """One stream at up to ~rate Hz over DEALER, recording every answer."""

    def __init__(self, endpoint, sid, rate=200.0):
        super().__init__(daemon=True)
        self.endpoint, self.sid, self.period = endpoint, sid, 1.0 / rate
        self.stop_flag = threading.Event()
        self.answers: dict[int, wire.Message] = {}
        self.sent = 0
        self.error: BaseException | None = None

    def run(self):
        c = zmq.Context()
        s = c.socket(zmq.DEALER)
        s.setsockopt(zmq.LINGER, 0)
        try:
            s.connect(self.endpoint)
            row = np.arange(len(CH), dtype=float)
            row[0] = np.nan
            # a handshake first, so the connection is up before the paced frames start (frames
            # queued while connecting would arrive together and be conflated, rightly)
            s.send(wire.encode(wire.Hello(self.sid, CH)))
            if not s.poll(5000):
                raise TimeoutError("no hello-ack")
            s.recv()
            # lock-step (each frame waits for its answer, like a REQ client): continuous traffic
            # during the reloads, and no frame can be conflated however slow the machine is
            while not self.stop_flag.is_set():
                s.send(frame(self.sid, self.sent, row))
                self.sent += 1
                if not s.poll(10000):
                    raise TimeoutError(f"frame {self.sent - 1} not answered within 10 s")
                m = wire.decode(s.recv())
                self.answers[m.seq] = m
                time.sleep(self.period)  # (pacing, not waiting: a stream at most 1/period Hz)
        except BaseException as e:  # surfaced by the test
            self.error = e
        finally:
            s.close(0)
            c.term()


def test_sighup_reload_under_traffic_loses_no_frame_and_bad_file_keeps_old_model(tmp_path, daemons):
    path = hold_file(tmp_path / "walk.npz", 10.0)
    d = daemons(write_config(tmp_path, {"walk": {"file": path}}))
    snd = Sender(d.endpoints["router"], "live")
    snd.start()
    try:
        wait_until(lambda: len(snd.answers) >= 40, 30, "40 answers before the first reload")
        hold_file(tmp_path / "walk.new.npz", 20.0)
        os.replace(tmp_path / "walk.new.npz", path)  # atomic, as `lacuna train` writes
        d.signal(signal.SIGHUP)
        rec = d.wait_for("reload_done", 30)
        assert rec["ok"] is True
        n1 = len(snd.answers)
        wait_until(lambda: len(snd.answers) >= n1 + 40, 30, "40 answers after the good reload")
        with open(path, "r+b") as fh:  # a truncated file: the reload must refuse it
            fh.truncate(100)
        d.signal(signal.SIGHUP)
        rec = d.wait_for("reload_done", 30)
        assert rec["ok"] is False
        refused = d.wait_for("reload_refused", 5)
        assert refused["model"] == "walk" and "truncated" in refused["error"]
        n2 = len(snd.answers)
        wait_until(lambda: len(snd.answers) >= n2 + 40, 30, "40 answers after the refused reload")
    finally:
        snd.stop_flag.set()
        snd.join(15)
    assert snd.error is None
    assert snd.sent > 100  # (40 answers before, between and after the reloads)
    # every frame answered with a fill: nothing lost, dropped or conflated across both reloads
    assert sorted(snd.answers) == list(range(snd.sent))
    assert [m for m in snd.answers.values() if not isinstance(m, wire.FillMsg)] == []
    # channel 0 is never observed: held at the model's mean, 10 before the swap and 20 after
    # (the swap restarts the filter state with the new model), never anything else
    vals = [snd.answers[i].angles[0] for i in range(snd.sent)]
    first20 = vals.index(20.0)
    assert set(vals[:first20]) == {10.0} and set(vals[first20:]) == {20.0}
    st = loadgen_status(d)
    assert st["reload"]["ok"] is False and "walk" in st["reload"]["errors"]
    assert st["counters"]["reloads"] == 1 and st["counters"]["reload_failures"] == 1


# ---- SIGTERM, sd_notify ---------------------------------------------------------------------------
def test_sigterm_drains_and_sd_notify_messages(tmp_path, daemons, ctx):
    sock_path = str(tmp_path / "notify.sock")
    ns = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    ns.bind(sock_path)
    ns.settimeout(10.0)
    try:
        d = daemons(write_config(tmp_path, {"walk": {"file": hold_file(tmp_path / "h.npz", 0.0)}}),
                    env={"NOTIFY_SOCKET": sock_path, "WATCHDOG_USEC": "200000"})

        def until(pred, what):
            end = time.monotonic() + 10
            while time.monotonic() < end:
                msg = ns.recv(4096).decode()
                if pred(msg):
                    return msg
            raise TimeoutError(what)

        first = until(lambda m: "READY=1" in m, "READY=1")
        assert "STATUS=" in first
        until(lambda m: m == "WATCHDOG=1", "WATCHDOG=1")
        until(lambda m: m == "WATCHDOG=1", "a second WATCHDOG=1")
        d.signal(signal.SIGHUP)
        rl = until(lambda m: "RELOADING=1" in m, "RELOADING=1")
        assert "MONOTONIC_USEC=" in rl
        until(lambda m: "READY=1" in m, "READY=1 after reload")
        # pipeline frames, then SIGTERM: whatever reached the daemon is answered (fewer frames
        # than the high-water mark, 100: this client reads its answers only at the end)
        s = dealer(ctx, d)
        n = 60
        for i in range(n):
            s.send(frame("t", i, np.zeros(len(CH))))
        # some of the frames are in (the rest may be in flight when SIGTERM lands: that is the point)
        wait_until(lambda: loadgen_status(d)["counters"].get("frames_in", 0) > 0, 10, "a first frame taken in")
        d.signal(signal.SIGTERM)
        until(lambda m: m == "STOPPING=1", "STOPPING=1")
        assert d.proc.wait(15) == 0
        stopped = d.wait_for("stopped", 5)
        answers = []
        while s.poll(500):
            answers.append(wire.decode(s.recv()))
        assert stopped["frames_in"] > 0
        assert len(answers) == stopped["frames_in"]  # every frame it took in was answered
        assert sum(isinstance(a, wire.FillMsg) for a in answers) == stopped["frames_out"]
    finally:
        ns.close()


def test_stop_drains_a_daemon_that_is_held_stopped(tmp_path, daemons, ctx):
    """A daemon held stopped (SIGSTOP: the starved soak, a debugger) when its harness stops it
    drains and exits 0: the harness continues it after SIGTERM.  Before, SIGTERM stayed pending on
    the stopped process until the SIGKILL fallback (exit -9), and a run interrupted there left a
    stopped ``lacuna serve`` on the machine."""
    d = daemons(write_config(tmp_path, {"walk": {"file": hold_file(tmp_path / "h.npz", 0.0)}}))
    s = dealer(ctx, d)
    s.send(frame("t", 0, np.zeros(len(CH))))
    assert isinstance(recv(s), wire.FillMsg)
    d.signal(signal.SIGSTOP)
    wait_until(lambda: _proc_state(d.proc.pid) == "T", 10, "the daemon stopped (state T)")
    assert d.stop(timeout_s=60) == 0
    stopped = d.wait_for("stopped", 5)
    assert stopped["frames_in"] == 1 and stopped["frames_out"] == 1


def _proc_state(pid: int) -> str:
    with open(f"/proc/{pid}/stat") as fh:
        return fh.read().rsplit(")", 1)[1].split()[0]


# ---- degrade --------------------------------------------------------------------------------------
def test_over_budget_steps_degrade_to_hold_and_say_so(tmp_path, daemons, ctx):
    rng = np.random.default_rng(1)
    # a nearest-neighbour model over 60000 training frames costs ~ms per step: far over a 0.05 ms budget
    NearestNeighbourModel(CH, rng.normal(size=(60000, len(CH))), np.ones(len(CH))).save(str(tmp_path / "nn.npz"))
    # (overdue = "serve": no frame can be answered within 0.05 ms, and "drop" would drop them all;
    # this test is about what the step does when it is over budget)
    d = daemons(write_config(tmp_path, {"nn": {"file": str(tmp_path / "nn.npz")}}, budget_ms=0.05, overdue="serve"))
    s = dealer(ctx, d)
    row = np.arange(len(CH), dtype=float)
    s.send(frame("slow", 0, row))
    prev = recv(s)
    row[3] = np.nan
    held = 0
    for seq in range(1, 6):
        s.send(frame("slow", seq, row))
        m = recv(s)
        assert m.filled[3]
        if m.status == "degraded":  # held: hold-last-value has no std (NaN, not 0)
            assert np.isnan(m.std[3]) and m.angles[3] == prev.angles[3]
            held += 1
        else:  # a probe: one real nn step per second keeps its cost estimate honest
            assert m.status == "ok" and m.std[3] == 0.0
        prev = m
    assert held >= 3
    st = loadgen_status(d)
    assert st["streams"]["slow"]["held"] + st["probes"] == 6
    assert st["counters"]["degraded"] == st["counters"]["degraded_held"] == st["streams"]["slow"]["held"]


# ---- SUB ingest, expiry, control reload, real data --------------------------------------------------
def test_sub_ingest_from_a_capture_pub_and_idle_expiry(tmp_path, daemons, ctx):
    cap = ctx(zmq.PUB)  # the capture system's publisher; the daemon connects to it
    port = cap.bind_to_random_port("tcp://127.0.0.1")
    cfg = write_config(tmp_path, {"floor": {"builtin": "passthrough"}},
                       extra=f'sub = ["tcp://127.0.0.1:{port}"]\n')
    cfg_text = open(cfg).read().replace("idle_timeout_s = 60", "idle_timeout_s = 0.5")
    open(cfg, "w").write(cfg_text)
    d = daemons(cfg)
    out = ctx(zmq.SUB)
    out.setsockopt(zmq.SUBSCRIBE, b"")
    out.connect(d.endpoints["pub"])
    got = None
    for seq in range(100):  # until both subscriptions are up (slow joiner), at most 10 s
        cap.send_multipart([b"mocap", frame("stage", seq, [1.0, 2.0])])
        if out.poll(100):
            topic, body = out.recv_multipart()
            got = wire.decode(body)
            break
    assert isinstance(got, wire.FillMsg) and topic == b"stage" and got.angles.tolist() == [1.0, 2.0]
    d.wait_for("stream_expired", 10, stream="stage")  # idle longer than idle_timeout_s (0.5 s)
    st = loadgen_status(d)
    assert "stage" not in st["streams"] and st["expired"] == 1


def test_control_reload_answers_when_done_and_bad_config_keeps_serving(tmp_path, daemons, ctx):
    cfg = write_config(tmp_path, {"walk": {"file": hold_file(tmp_path / "h.npz", 1.0)}})
    d = daemons(cfg)
    s = dealer(ctx, d)
    s.send(frame("c", 0, np.full(len(CH), np.nan)))
    assert recv(s).angles[0] == 1.0
    hold_file(tmp_path / "h.npz", 2.0)
    s.send(wire.encode(wire.Control("reload")))
    r = recv(s, 30000)
    assert r.cmd == "reload" and r.ok and r.result["errors"] == {}
    s.send(frame("c", 1, np.full(len(CH), np.nan)))
    assert recv(s).angles[0] == 2.0
    open(cfg, "a").write("\n[daemon]\nbudget_ms = -3\n")  # a broken config (duplicate table too)
    s.send(wire.encode(wire.Control("reload")))
    r = recv(s, 30000)
    assert not r.ok and "config" in r.result["errors"] and str(cfg) in r.error
    s.send(frame("c", 2, np.full(len(CH), np.nan)))
    m = recv(s)
    assert isinstance(m, wire.FillMsg) and m.angles[0] == 2.0


def test_real_walk_through_daemon_matches_in_process_filler(tmp_path, daemons, ctx, data):
    """A real CMU walk with the left arm missing, through the daemon frame by frame, gives the
    same fill as the same model run in-process (float32 on the wire)."""
    from mocap.protocols import get_protocol

    proto = get_protocol("pan2009")
    ts = proto.training_set()
    model = HoldModel.fit(ts.sequences, ts.channels)
    model.save(str(tmp_path / "hold.npz"))
    case = proto.cases()[0]
    truth = case.truth[:240].astype(np.float32)
    miss = np.array([c.startswith(("lhumerus", "lradius", "lwrist")) for c in ts.channels])
    d = daemons(write_config(tmp_path, {"hold": {"file": str(tmp_path / "hold.npz")}}))
    s = dealer(ctx, d)
    s.send(wire.encode(wire.Hello("walk", list(ts.channels))))
    assert isinstance(recv(s), wire.HelloAck)
    sent = truth.copy()
    sent[:, miss] = np.nan
    got = []
    for t in range(sent.shape[0]):
        s.send(frame("walk", t, sent[t]))
        m = recv(s)
        assert isinstance(m, wire.FillMsg), m
        got.append(m)
    ref, ref_std = model.fill_offline(sent.astype(np.float64), ~np.isnan(sent))
    out = np.stack([m.angles for m in got])
    assert np.array_equal(out[:, ~miss], truth[:, ~miss])  # observed values come back exactly
    np.testing.assert_allclose(out, ref.astype(np.float32), rtol=0, atol=1e-4)
    assert all(m.filled[miss].all() and not m.filled[~miss].any() for m in got)
    np.testing.assert_allclose(np.stack([m.std for m in got]), ref_std.astype(np.float32), atol=1e-4)


def test_serve_check_validates_config_and_models(tmp_path):
    good = write_config(tmp_path, {"walk": {"file": hold_file(tmp_path / "h.npz", 0.0)}})
    r = subprocess.run([sys.executable, "-m", "lacuna.cli", "serve", "--check", "--config", good],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "model walk: ok" in r.stdout, r.stderr
    (tmp_path / "h.npz").write_bytes(b"PK\x03\x04 not really a zip")
    r = subprocess.run([sys.executable, "-m", "lacuna.cli", "serve", "--check", "--config", good],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "h.npz" in r.stderr and "model walk" in r.stderr
    r = subprocess.run([sys.executable, "-m", "lacuna.cli", "serve", "--config", str(tmp_path / "missing.toml")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.startswith("lacuna: error:") and "missing.toml" in r.stderr


def test_start_logs_each_model_loading_and_loaded_before_ready(tmp_path, daemons):
    # the first start after an install compiles kernels for a minute: the log says which model
    cfg = write_config(tmp_path, {"walk": {"file": hold_file(tmp_path / "h.npz", 0.0)}, "floor": {"builtin": "passthrough"}},
                       default="walk")
    d = daemons(cfg)
    recs = d.records()
    events = [(r["event"], r.get("model")) for r in recs if r["event"] in ("loading", "loaded", "ready")]
    assert events == [("loading", "walk"), ("loaded", "walk"), ("loading", "floor"), ("loaded", "floor"),
                      ("ready", None)]
    loaded = [r for r in recs if r["event"] == "loaded"]
    assert all(isinstance(r["seconds"], float) and r["seconds"] >= 0 for r in loaded)
    assert recs[0]["file"] == str(tmp_path / "h.npz") and recs[2]["builtin"] == "passthrough"


def test_osc_answers_go_to_the_configured_send_address(tmp_path, daemons):
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    out.bind(("127.0.0.1", 0))
    out.settimeout(5.0)
    src = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    src.bind(("127.0.0.1", 0))
    src.settimeout(0.5)
    try:
        cfg = write_config(tmp_path, {"floor": {"builtin": "passthrough"}}, osc=True,
                           extra=f'send = "127.0.0.1:{out.getsockname()[1]}"\n')
        d = daemons(cfg)
        host, port = d.endpoints["osc"].rsplit(":", 1)
        src.sendto(_osc_frame("o2", 3, [0.5, 0.25]), (host, int(port)))
        msgs = {m.address: m.params for m in OscBundle(out.recv(65535))}
        assert msgs["/lacuna/fill"][:2] == ["o2", 3] and msgs["/lacuna/fill"][7:] == [0.5, 0.25]
        with pytest.raises(socket.timeout):
            src.recv(65535)  # nothing goes back to the sender when osc.send is set
    finally:
        out.close()
        src.close()


def test_a_flood_of_bad_messages_is_counted_in_full_but_logged_sparingly(tmp_path, daemons, ctx):
    d = daemons(write_config(tmp_path, {"floor": {"builtin": "passthrough"}}))
    s = dealer(ctx, d)
    n = 300
    for i in range(n):
        s.send(b"\xc1" + bytes([i % 256]))
    errors = [recv(s) for _ in range(n)]
    assert all(isinstance(e, wire.ErrorMsg) and e.reason == "not_msgpack" for e in errors)
    st = loadgen_status(d)
    assert st["rejected"] == {"not_msgpack": n}
    d.wait_for("rejected_not_logged", 5)

    def log_counts() -> tuple[int, int]:  # every rejection is either a log line or in a summary line
        return (sum(1 for r in d.log if r.get("event") == "rejected"),
                sum(r["count"] for r in d.log if r.get("event") == "rejected_not_logged"))

    wait_until(lambda: sum(log_counts()) >= n, 5, "every rejection logged or summed", 0.1)
    logged, summed = log_counts()
    assert logged + summed == n and logged <= n // 2


def test_second_daemon_on_a_taken_port_fails_with_a_clear_error(tmp_path, daemons):
    d = daemons(write_config(tmp_path, {"floor": {"builtin": "passthrough"}}))
    taken = d.endpoints["router"]
    cfg2 = tmp_path / "second.toml"
    cfg2.write_text(f'[models.floor]\nbuiltin = "passthrough"\n[zmq]\nrouter = "{taken}"\n')
    r = subprocess.run([sys.executable, "-m", "lacuna.cli", "serve", "--config", str(cfg2)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    # (after the log's loading/loaded lines of its model: the bind comes after the models load)
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("lacuna: error: zmq.router") and taken in last and "cannot bind" in last


@pytest.mark.slow
def test_hlm_model_through_daemon_equals_in_process_stream_with_style_and_phase(tmp_path, daemons, ctx, small_walk_hlm):
    """A real HLM (trained in seconds on three subject-35 walks) serves a held-out walk with the
    left arm missing: the daemon's fills equal the model's own causal stream fed the same float32
    frames, and every reply carries the style posterior and the gait phase."""
    import shutil

    from mocap.datasets import load_trial

    shutil.copy(small_walk_hlm, tmp_path / "hlm.npz")
    channels = list(load_trial("35_01").channels)
    test = load_trial("35_08").frames[:150].astype(np.float32)
    miss = np.array([c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "lhand") for c in channels])
    sent = test.copy()
    sent[:, miss] = np.nan
    d = daemons(write_config(tmp_path, {"hlm": {"file": str(tmp_path / "hlm.npz")}}, budget_ms=1000.0))
    s = dealer(ctx, d)
    s.send(wire.encode(wire.Hello("walk", channels)))
    assert isinstance(recv(s), wire.HelloAck)
    from lacuna.modelfile import load_model

    ref_model = load_model(str(tmp_path / "hlm.npz"))  # the same file the daemon loaded
    st = ref_model.stream()
    for t in range(sent.shape[0]):
        s.send(frame("walk", t, sent[t]))
        m = recv(s, 30000)
        assert isinstance(m, wire.FillMsg) and m.status == "ok", m
        ref = st.step(sent[t].astype(np.float64), ~np.isnan(sent[t]))
        assert np.array_equal(m.angles[~miss], test[t, ~miss])
        np.testing.assert_allclose(m.angles, ref.frame.astype(np.float32), atol=1e-3)
        np.testing.assert_allclose(m.std, ref.std.astype(np.float32), atol=1e-3)
        assert m.filled[miss].all() and not m.filled[~miss].any()
        assert m.style is not None and m.style.shape == (2,) and abs(float(m.style.sum()) - 1.0) < 1e-4
        assert m.phase is not None and 0.0 <= m.phase < 1.0
        np.testing.assert_allclose(m.style, np.asarray(ref.extras["style"], np.float32), atol=1e-5)


def test_busy_poll_serves_round_trips_stops_spinning_when_idle_and_still_stops_on_sigterm(tmp_path, daemons, ctx):
    """busy_poll_ms: the daemon spins on its sockets while frames flow.  It must answer exactly as
    without it, go back to sleeping in poll once the traffic pauses, and still see SIGTERM while
    spinning.  "Sleeping in poll" is read from the kernel (the serving thread's wait channel in
    /proc), not from a CPU-time figure: bench/busy_poll_idle.py measures the CPU it costs."""
    wchan = "/proc/{pid}/task/{pid}/wchan"
    if not os.path.exists(wchan.format(pid=os.getpid())):
        pytest.skip("no /proc/<pid>/task/<tid>/wchan on this system: cannot see where the daemon sleeps")

    def asleep_in_poll() -> bool:  # the serving (main) thread blocked in poll(2), not spinning
        with open(wchan.format(pid=d.proc.pid)) as fh:
            return "poll" in fh.read()

    cfg = write_config(tmp_path, {"walk": {"file": hold_file(tmp_path / "h.npz", 0.0)}})
    with open(cfg) as fh:
        text = fh.read().replace("[daemon]\n", "[daemon]\nbusy_poll_ms = 50\n", 1)
    with open(cfg, "w") as fh:
        fh.write(text)
    d = daemons(cfg)
    s = dealer(ctx, d)
    vals = np.arange(len(CH), dtype=np.float32)
    for i in range(200):
        obs = np.ones(len(CH), bool)
        obs[i % len(CH)] = False
        s.send(frame("spin", i, vals, obs))
        m = recv(s)
        assert isinstance(m, wire.FillMsg) and m.seq == i and m.status == "ok"
        assert np.array_equal(m.angles[obs], vals[obs]) and m.filled[i % len(CH)]
    # past the 50 ms busy window it blocks in poll (while spinning it only ever polls with timeout 0,
    # which never sleeps there)
    wait_until(asleep_in_poll, 10, "the daemon's serving thread asleep in poll after the traffic stopped", 0.02)
    # SIGTERM in the middle of a burst (while it spins) drains and exits cleanly
    for i in range(200, 230):
        s.send(frame("spin", i, vals))
    d.signal(signal.SIGTERM)
    assert d.proc.wait(15) == 0
    answers = []
    while s.poll(500):
        answers.append(wire.decode(s.recv()))
    assert len(answers) == d.wait_for("stopped", 5)["frames_in"] - 200


def test_busy_poll_config_is_validated(tmp_path):
    from daemon import config as config_mod

    for bad, needle in (("-1", "must be between"), ("nan", "must be between"), ("\"fast\"", "must be a")):
        p = tmp_path / "bad.toml"
        p.write_text(f"[daemon]\nbusy_poll_ms = {bad}\n[models.m]\nbuiltin = \"passthrough\"\n")
        with pytest.raises(config_mod.ConfigError, match=f"daemon.busy_poll_ms {needle}"):
            config_mod.load(str(p))


# ---- bundles -----------------------------------------------------------------------------------
def _bundle(*frames):
    """A `frames` message of raw frame maps (elements may be anything: the daemon reads each one)."""
    import msgpack

    return msgpack.packb({"v": 1, "type": "frames", "frames": list(frames)}, use_bin_type=True)


def _fmap(sid, seq, values, observed=None):
    m = wire.to_map(wire.Frame(sid, seq, seq / 120.0, np.asarray(values, np.float32), observed))
    del m["v"], m["type"]
    return m


def test_a_bundle_of_streams_is_served_as_single_frames_and_answered_in_one_replies(tmp_path, daemons, ctx):
    """One `frames` message carrying four streams (one frame malformed, one too narrow for its
    stream) gets one `replies`: a fill per good frame equal to what the same frame alone gets,
    an error naming each bad one.  Later bundles see the sessions the first one opened."""
    d = daemons(write_config(tmp_path, {"walk": {"file": hold_file(tmp_path / "h.npz", 0.0)}}))
    s, single = dealer(ctx, d), dealer(ctx, d)
    C = len(CH)
    vals = np.arange(1, C + 1, dtype=np.float32)
    obs = np.ones(C, bool)
    obs[[1, 5]] = False
    s.send(_bundle(_fmap("p1", 0, vals, obs), {"stream": "p2", "seq": 0, "t": 0.0, "angles": b"\0" * 5},
                   _fmap("p3", 0, np.where(obs, vals, np.nan)), _fmap("p4", 0, vals)))
    r = recv(s)
    assert isinstance(r, wire.Replies), r
    by = {(m.stream, type(m).__name__): m for m in r.items}
    assert len(r.items) == 4 and set(by) == {("p1", "FillMsg"), ("p2", "ErrorMsg"), ("p3", "FillMsg"), ("p4", "FillMsg")}
    assert by["p2", "ErrorMsg"].reason == "bad_length" and by["p2", "ErrorMsg"].seq == 0
    for sid in ("p1", "p3"):
        m = by[sid, "FillMsg"]
        assert m.status == "ok" and m.model == "walk" and m.filled.tolist() == (~obs).tolist()
        assert np.array_equal(m.angles[obs], vals[obs]) and np.isfinite(m.angles).all()
    single.send(frame("alone", 0, vals, obs))                  # the same frame on its own: the same fill
    alone = recv(single)
    assert np.array_equal(alone.angles, by["p1", "FillMsg"].angles) and np.array_equal(alone.std, by["p1", "FillMsg"].std)
    # second bundle: a late frame, a frame of the wrong width for its (now open) stream, a good one
    s.send(_bundle(_fmap("p1", 0, vals), _fmap("p3", 1, vals[:3]), _fmap("p4", 1, vals, obs)))
    r = recv(s)
    by = {m.stream: m for m in r.items}
    assert isinstance(by["p1"], wire.Drop) and by["p1"].reason == "duplicate"
    assert isinstance(by["p3"], wire.ErrorMsg) and by["p3"].reason == "width" and by["p3"].seq == 1
    assert isinstance(by["p4"], wire.FillMsg) and by["p4"].seq == 1 and by["p4"].filled.tolist() == (~obs).tolist()
    # a bundle that is not a list of frames is refused whole, with one plain error
    s.send(_bundle())
    e = recv(s)
    assert isinstance(e, wire.ErrorMsg) and e.reason == "bad_length"
    st = loadgen_status(d)
    from daemon.cli import render

    assert "bundles_in 2" in render(st)
    # two bundles read (the empty one was refused before it was one); p2's element never became a frame
    assert st["counters"]["bundles_in"] == 2 and st["counters"]["frames_in"] == 3 + 1 + 3
    assert st["streams"]["p1"]["frames_out"] == 1 and st["streams"]["p4"]["frames_out"] == 2
    assert st["rejected"] == {"bad_length": 2, "width": 1}


def test_bundles_on_pull_publish_each_stream_on_pub(tmp_path, daemons, ctx):
    d = daemons(write_config(tmp_path, {"floor": {"builtin": "passthrough"}}, pull=True))
    sub = ctx(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    sub.connect(d.endpoints["pub"])
    push = ctx(zmq.PUSH)
    push.connect(d.endpoints["pull"])
    got: dict[str, wire.Message] = {}
    deadline = time.monotonic() + 10
    seq = 0
    while len(got) < 3 and time.monotonic() < deadline:   # PUB drops what it sends before SUB joined
        push.send(_bundle(*(_fmap(f"q{i}", seq, [1.0, float(i)]) for i in range(3))))
        seq += 1
        while sub.poll(200):
            topic, body = sub.recv_multipart()
            m = wire.decode(body)
            assert isinstance(m, wire.FillMsg) and topic == m.stream.encode() and m.angles[1] == float(m.stream[1])
            got[m.stream] = m
    assert set(got) == {"q0", "q1", "q2"}


# ---- PM QoS CPU latency request ------------------------------------------------------------------
def _fds_to(pid: int, target: str) -> int:
    n = 0
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            n += os.readlink(f"/proc/{pid}/fd/{fd}") == target
        except OSError:
            pass
    return n


def test_cpu_latency_request_is_held_while_serving_and_follows_reload(tmp_path, daemons, ctx):
    """daemon.cpu_latency_us = 0: the daemon holds /dev/cpu_dma_latency open with 0 written (the
    kernel then reads back 0 as the machine's bound), and a reload without the key lets it go.
    Where the device cannot be written (not root), the daemon says so in its log and status,
    counts it, and serves all the same."""
    from daemon.pmqos import DEVICE

    cfg = write_config(tmp_path, {"floor": {"builtin": "passthrough"}})
    text = open(cfg).read()
    with open(cfg, "w") as fh:
        fh.write(text.replace("[daemon]\n", "[daemon]\ncpu_latency_us = 0\n", 1))
    d = daemons(cfg)
    s = dealer(ctx, d)
    s.send(frame("q", 0, [1.0, 2.0]))
    assert isinstance(recv(s), wire.FillMsg)
    q = loadgen_status(d)["cpu_latency"]
    assert q["requested_us"] == 0 and q["device"] == DEVICE
    if os.access(DEVICE, os.W_OK):
        assert q["held"] and q["effective_us"] == 0 and q["error"] is None
        from daemon.cli import render

        assert "cpu latency request: 0 us, held (machine-wide bound now 0 us)" in render(loadgen_status(d))
        assert _fds_to(d.proc.pid, DEVICE) == 1
        d.wait_for("cpu_latency", 5, requested_us=0)
        with open(cfg, "w") as fh:
            fh.write(text)                                   # the key removed: the request goes
        d.signal(signal.SIGHUP)
        d.wait_for("reload_done", 10)
        q = loadgen_status(d)["cpu_latency"]
        assert not q["held"] and q["requested_us"] is None and _fds_to(d.proc.pid, DEVICE) == 0
    else:
        assert not q["held"] and "cannot open" in q["error"]
        assert d.wait_for("cpu_latency_refused", 5)["requested_us"] == 0
        assert loadgen_status(d)["counters"]["cpu_latency_refused"] == 1
    s.send(frame("q", 1, [1.0, 2.0]))
    assert isinstance(recv(s), wire.FillMsg)


def test_cpu_latency_refused_is_reported_and_the_daemon_serves_on(tmp_path, daemons, ctx):
    """The device is root-only: a daemon without the right to it logs cpu_latency_refused,
    counts it, shows the error in status and serves.  As root the test runs the daemon as
    nobody (setpriv) so the refusal is a real one either way."""
    import shutil
    import tempfile

    if os.geteuid() == 0 and shutil.which("setpriv") is None:
        pytest.skip("running as root without setpriv: no way to start an unprivileged daemon here")
    d_dir = tempfile.mkdtemp(prefix="lacuna-qos-")              # readable by the unprivileged daemon
    os.chmod(d_dir, 0o755)
    cfg = write_config(tmp_path, {"floor": {"builtin": "passthrough"}})
    dst = os.path.join(d_dir, "lacuna.toml")
    with open(cfg) as fh, open(dst, "w") as out:
        out.write(fh.read().replace("[daemon]\n", "[daemon]\ncpu_latency_us = 0\n", 1))
    os.chmod(dst, 0o644)
    python = sys.executable
    if os.geteuid() == 0:
        python = os.path.join(d_dir, "python-as-nobody")
        with open(python, "w") as fh:
            fh.write(f"#!/bin/sh\nexec setpriv --reuid=65534 --regid=65534 --clear-groups {sys.executable} \"$@\"\n")
        os.chmod(python, 0o755)
    d = DaemonProcess(dst, env={"HOME": d_dir}, python=python)
    try:
        d.start()
        rec = d.wait_for("cpu_latency_refused", 5)
        assert rec["requested_us"] == 0 and "cpu_dma_latency" in rec["error"]
        s = ctx(zmq.DEALER)
        s.connect(d.endpoints["router"])
        s.send(frame("q", 0, [1.0, 2.0]))
        assert isinstance(recv(s), wire.FillMsg)
        st = loadgen_status(d)
        assert st["counters"]["cpu_latency_refused"] == 1 and st["pid"] != os.getpid()
        q = st["cpu_latency"]
        assert not q["held"] and q["requested_us"] == 0 and q["error"].startswith("cannot open")
        from daemon.cli import render

        assert "cpu latency request: 0 us, NOT HELD: cannot open /dev/cpu_dma_latency" in render(st)
    finally:
        d.stop()
        shutil.rmtree(d_dir, ignore_errors=True)


def test_cpu_latency_request_mechanics_on_real_files(tmp_path):
    from daemon import config as config_mod
    from daemon.pmqos import CpuLatency

    missing = CpuLatency(str(tmp_path / "no-such-device"))
    assert not missing.request(0) and "cannot open" in missing.error and not missing.held
    assert missing.info()["effective_us"] is None
    f = tmp_path / "dev"
    f.write_bytes(b"")
    q = CpuLatency(str(f))
    assert q.request(25) and q.held and q.error is None
    assert q.effective_us() == 25                       # a plain file reads back what was written
    q.request(None)                                     # no request: the file is closed
    assert not q.held and q.requested_us is None
    for bad, needle in (("-1", "must be between"), ("1.5", "must be an integer"), ("\"low\"", "must be an integer")):
        p = tmp_path / "bad.toml"
        p.write_text(f"[daemon]\ncpu_latency_us = {bad}\n[models.m]\nbuiltin = \"passthrough\"\n")
        with pytest.raises(config_mod.ConfigError, match=f"daemon.cpu_latency_us {needle}"):
            config_mod.load(str(p))


def test_osc_fill_whose_gap_overflows_int32_is_answered_saturated_and_the_daemon_serves_on(tmp_path, daemons):
    """OSC's fill carries the gap (frames skipped since the last one served) as an int32; a peer
    whose seq jumps by 2^40 made the encoder raise inside the tick, and the turn was lost for every
    stream in it.  The gap saturates at 2^31 - 1 instead; the same stream and another go on."""
    d = daemons(write_config(tmp_path, {"walk": {"file": hold_file(tmp_path / "h.npz", -4.0)}}, osc=True))
    host, port = d.endpoints["osc"].rsplit(":", 1)
    u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    u.bind(("127.0.0.1", 0))
    u.settimeout(5.0)

    def frame64(sid, seq):
        b = OscMessageBuilder("/lacuna/frame")
        b.add_arg(sid, "s")
        b.add_arg(seq, "h")
        b.add_arg(0.0, "d")
        for v in [1.0, float("nan"), 2.5, 0.0, 1.0, 2.0, 3.0, 4.0]:
            b.add_arg(v, "f")
        return b.build().dgram

    def fill_of(data):
        return {m.address: m.params for m in OscBundle(data)}["/lacuna/fill"]

    try:
        for sid, seq, gap in [("far", 0, 0), ("far", 1 << 40, 2**31 - 1), ("far", (1 << 40) + 1, 0), ("near", 0, 0)]:
            u.sendto(frame64(sid, seq), (host, int(port)))
            fill = fill_of(u.recv(65535))
            assert fill[:2] == [sid, seq] and fill[6] == gap and fill[3] == "ok"
    finally:
        u.close()
