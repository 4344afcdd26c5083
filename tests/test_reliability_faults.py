"""Issue 7, item 3: faults, each against a real daemon process on real loopback sockets.

* a client vanishes mid-stream (socket closed with answers pending; a client process SIGKILLed;
  an OSC sender whose port is gone): the daemon keeps serving, the stream expires;
* the daemon is SIGKILLed and restarted by a supervisor (Restart=on-failure semantics, as a
  thread here): request/reply clients reconnect and their streams resume, subscribers too;
* the model file is replaced by a truncated (or otherwise broken) one and SIGHUP'd: the old
  model keeps serving every frame, the log says why the file was refused;
* the output consumer is too slow (a SUB that never reads, a DEALER that never reads, an OSC
  destination that never reads): the daemon drops that output and never blocks;
* capture timestamps jump (backwards, far forward, zero, huge) and sequence numbers jump: frames
  are ordered by seq only, t is echoed untouched, a huge seq gap restarts the filter instead of
  predicting 10^12 frames.
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import textwrap
import time

import fuzzgen
import numpy as np
import pytest
import zmq
from reliability_daemon import Daemon, LockStep, Sockets, Supervisor, control, recv_msg, status, write_config
from waiting import wait_until

from daemon import wire
from lacuna import modelfile
from mocap.baselines import HoldModel
from mocap.datasets import load_trial


@pytest.fixture(scope="module")
def walk(data):
    """Real motion (subject 35 walk) with markers dropping out, and a hold model fitted to it."""
    m = load_trial("35_01")
    rng = np.random.default_rng(7)
    f = m.frames.astype(np.float32)
    for _ in range(30):
        c = rng.integers(6, f.shape[1])
        t0 = rng.integers(0, f.shape[0] - 30)
        f[t0:t0 + rng.integers(5, 30), c] = np.nan
    return f, list(m.channels), HoldModel.fit([m.frames], list(m.channels))


def all_filled(ls: LockStep, model: str | None = None) -> None:
    """Every seq the client sent has a fill (no drop, no error), observed values untouched.

    A frame sent again after a timeout may be answered ``duplicate``: the daemon had served
    it, and the fill went to the socket the client had just closed."""
    assert ls.problems == [], ls.problems[:3]
    seqs = sorted(ls.answers)
    assert seqs == list(range(len(seqs))) and len(seqs) > 0
    for seq, m in ls.answers.items():
        if seq in ls.retried and isinstance(m, wire.Drop) and m.reason == "duplicate":
            continue
        assert isinstance(m, wire.FillMsg), (seq, m)
        f = ls.frames[seq % len(ls.frames)]
        obs = np.isfinite(f)
        assert np.array_equal(m.angles[obs], f[obs]) and np.isfinite(m.angles).all()
        if model:
            assert m.model == model


# ---- a client vanishes ---------------------------------------------------------------------------
VANISHING_CLIENT = textwrap.dedent("""
    import sys, time, numpy as np, zmq
    from daemon import wire
    ctx = zmq.Context(); s = ctx.socket(zmq.DEALER); s.connect(sys.argv[1])
    C = int(sys.argv[2])
    for seq in range(100000):  # pipelined, never reads an answer; killed mid-stream
        s.send(wire.encode(wire.Frame("ghost", seq, seq / 120.0, np.zeros(C, np.float32))))
        if seq == 200:
            print("sending", flush=True)
        time.sleep(0.0005)  # (pacing, not waiting: a stream at ~2 kHz, killed mid-stream)
""")


def test_client_vanishing_mid_stream_leaves_the_daemon_serving(tmp_path, walk):
    frames, channels, model = walk
    model.save(str(tmp_path / "walk.npz"))
    ep = write_config(tmp_path / "lacuna.toml", {"walk": {"file": "walk.npz"}}, osc=True,
                      daemon={"idle_timeout_s": 1.0})
    d = Daemon(tmp_path / "lacuna.toml", tmp_path / "daemon.log").start()
    S = Sockets()
    good = LockStep(ep["router"], "good", frames)
    ghost = None
    try:
        good.start()
        # 1. a client process killed with SIGKILL while frames are in flight
        ghost = subprocess.Popen([sys.executable, "-c", VANISHING_CLIENT, ep["router"], str(len(channels))],
                                 stdout=subprocess.PIPE, text=True)
        assert ghost.stdout.readline().strip() == "sending"
        ghost.kill()
        ghost.wait(10)
        # 2. a socket closed (linger 0) with frames sent and their answers never read
        s = S.make(zmq.DEALER, ep["router"])
        for seq in range(300):
            s.send(wire.encode(wire.Frame("closer", seq, 0.0, frames[seq % len(frames)])))
        s.close(0)
        # 3. an OSC sender whose port is closed before the answers come back (ICMP port unreachable)
        u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        u.bind(("127.0.0.1", 0))
        for seq in range(50):
            u.sendto(fuzzgen.osc_frame("oscghost", seq, 0.0, frames[seq % len(frames)]), ep["osc"])
        u.close()
        n0 = len(good.answers)
        d.wait_for("stream_expired", 10, stream="ghost")
        d.wait_for("stream_expired", 10, stream="oscghost")
        wait_until(lambda: len(good.answers) > n0, 10, "the good stream answered after the expiries")  # served all along
        st = status(S, ep["router"])
        assert "ghost" not in st["streams"] and "oscghost" not in st["streams"]
        assert st["expired"] >= 2
        # a new OSC client is served after the ICMP errors
        u2 = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        u2.bind(("127.0.0.1", 0))
        u2.settimeout(5)
        try:
            u2.sendto(fuzzgen.osc_frame("osc2", 0, 0.0, frames[0]), ep["osc"])
            assert b"/lacuna/fill" in u2.recv(65535)
        finally:
            u2.close()
        good.finish()
        all_filled(good, "walk")
        assert d.alive()
    finally:
        if ghost is not None and ghost.poll() is None:
            ghost.kill()
        good.stop_flag.set()
        S.close()
        d.stop()


# ---- SIGKILL and a supervisor ----------------------------------------------------------------------
def test_daemon_sigkilled_is_restarted_and_clients_resume(tmp_path, walk):
    frames, channels, model = walk
    model.save(str(tmp_path / "walk.npz"))
    ep = write_config(tmp_path / "lacuna.toml", {"walk": {"file": "walk.npz"}}, pull=True)
    sup = Supervisor(Daemon(tmp_path / "lacuna.toml", tmp_path / "daemon.log")).start()
    S = Sockets()
    # plugins that handshake, as the client library does: a reconnect on a fresh socket sends the
    # hello with its claim again, which takes the stream back from the old socket's connection
    # (a frame in flight at the kill can reach the new daemon through the old socket's own
    # reconnect and open the stream there; without the claim the plugin would wait for idle expiry)
    clients = [LockStep(ep["router"], f"performer{i}", frames, reconnect_ms=500, hello=list(channels))
               for i in range(3)]
    try:
        sub = S.make(zmq.SUB, ep["pub"])
        sub.setsockopt(zmq.SUBSCRIBE, b"pushed")
        push = S.make(zmq.PUSH, ep["pull"])
        for c in clients:
            c.start()
        wait_until(lambda: all(len(c.answers) > 10 for c in clients), 30, "10 answers to each client")
        before = {c.sid: len(c.answers) for c in clients}
        pid = sup.daemon.pid
        os.kill(pid, signal.SIGKILL)
        t_kill = time.perf_counter()
        wait_until(lambda: sup.restarts >= 1, 60, f"the supervisor's restart (errors: {sup.errors})")
        assert sup.restarts == 1 and sup.daemon.pid != pid, sup.errors
        # every client's stream goes on: answers for new sequence numbers from the new daemon
        wait_until(lambda: all(len(c.answers) >= before[c.sid] + 50 for c in clients), 60,
                   "50 more answers to each client from the restarted daemon")
        resumed = min(c.got_at[before[c.sid] + 5] for c in clients) - t_kill
        st = status(S, ep["router"])
        assert st["pid"] == sup.daemon.pid  # the restarted daemon answers
        for c in clients:  # (a frame in flight at the kill was sent again after 0.5 s: c.retries)
            assert c.sid in st["streams"] and st["streams"][c.sid]["frames_out"] >= 45
        # the PULL/PUB path reconnects by itself too (ZeroMQ reconnects both sockets)
        got = None
        for seq in range(200):
            push.send(wire.encode(wire.Frame("pushed", seq, 0.0, frames[seq % len(frames)])))
            if sub.poll(50):
                got = sub.recv_multipart()
                break
        assert got is not None and got[0] == b"pushed" and isinstance(wire.decode(got[1]), wire.FillMsg)
        for c in clients:
            c.finish()
            all_filled(c, "walk")
        print(f"\nSIGKILL -> restarted by supervisor -> 3 request/reply streams served again after {resumed:.2f} s "
              f"(reconnect timeout 0.5 s; retries {[c.retries for c in clients]})")
    finally:
        for c in clients:
            c.stop_flag.set()
        S.close()
        sup.stop()


# ---- a broken model file and SIGHUP ----------------------------------------------------------------
def _broken_files(path: str, good: bytes, C: int):
    """(description, writer, words the refusal must contain) for each way a model file can be bad."""
    def write(b: bytes):
        return lambda: open(path, "wb").write(b)

    def save(meta, arrays):
        return lambda: modelfile.save_arrays(path, {"method": "hold", "channels": [f"c{i}" for i in range(C)], **meta}, arrays)

    ok = {"mean": np.zeros(C), "std": np.ones(C)}
    return [
        ("truncated to half", write(good[: len(good) // 2]), "truncated"),
        ("truncated by one byte", write(good[:-1]), "truncated"),
        ("truncated to 10 bytes", write(good[:10]), "truncated"),
        ("empty", write(b""), "truncated"),
        ("garbage", write(os.urandom(4096)), "truncated"),
        ("NaN in an array", save({}, {"mean": np.full(C, np.nan), "std": np.ones(C)}), "NaN"),
        ("format version from the future", save({"format_version": 99}, ok), "format_version"),
        ("wrong array shape", save({}, {"mean": np.zeros(C + 1), "std": np.ones(C)}), "shape"),
        ("unknown method", lambda: modelfile.save_arrays(path, {"method": "nope", "channels": ["a"]}, ok), "unknown method"),
        ("not causal", lambda: modelfile.save_arrays(path, {"method": "interp", "channels": [f"c{i}" for i in range(C)]}, ok),
         "causal"),
        ("deleted", lambda: os.remove(path), "cannot read"),
    ]


def test_broken_model_file_on_sighup_keeps_the_old_model_serving(tmp_path, walk):
    frames, channels, model = walk
    path = str(tmp_path / "walk.npz")
    model.save(path)
    good_bytes = open(path, "rb").read()
    write_config(tmp_path / "lacuna.toml", {"walk": {"file": "walk.npz"}})
    ep = write_config(tmp_path / "lacuna.toml", {"walk": {"file": "walk.npz"}})
    d = Daemon(tmp_path / "lacuna.toml", tmp_path / "daemon.log").start()
    S = Sockets()
    ls = LockStep(ep["router"], "take1", frames, hello=channels)
    try:
        ls.start()
        for what, breaker, words in _broken_files(path, good_bytes, len(channels)):
            breaker()
            n0 = len(ls.answers)
            d.signal(signal.SIGHUP)
            rec = d.wait_for("reload_refused", 15, model="walk")
            assert words in rec["error"], (what, rec["error"])
            assert "old model keeps serving" in rec["detail"]
            d.wait_for("reload_done", 15, ok=False)
            wait_until(lambda n0=n0: len(ls.answers) >= n0 + 5, 10, f"5 answers after refusing {what}")  # serving throughout
        st = status(S, ep["router"])
        assert st["reload"]["ok"] is False and "walk" in st["reload"]["errors"]
        assert st["counters"]["reload_failures"] == len(_broken_files(path, good_bytes, len(channels)))
        # a good file is taken on the next SIGHUP, still without losing a frame
        shifted = HoldModel(channels, model.mean_ + 1.0, model.std_)
        shifted.save(path)
        d.signal(signal.SIGHUP)
        d.wait_for("model_swapped", 15, model="walk")
        d.wait_for("reload_done", 15, ok=True)
        n_swap = len(ls.answers)
        wait_until(lambda: len(ls.answers) >= n_swap + 5, 10, "5 answers from the new model")
        ls.finish()
        all_filled(ls, "walk")
        assert ls.answers and all(m.status in ("ok", "degraded") for m in ls.answers.values())
        assert d.alive()
    finally:
        ls.stop_flag.set()
        S.close()
        d.stop()


# ---- a slow output consumer ------------------------------------------------------------------------
def test_slow_consumers_make_the_daemon_drop_output_never_block(tmp_path, walk):
    frames, channels, model = walk
    model.save(str(tmp_path / "walk.npz"))
    # the flood goes to a pass-through model with wide frames (9 KB per fill), so the stuck
    # consumers' kernel buffers (MBs on loopback) fill up and ZeroMQ has to drop
    # (overdue = "serve": a turn that reads thousands of flood messages can take longer than the
    # budget, and the good stream's frames read in it would be dropped `overdue`; this test is
    # about answers that cannot be sent, and wants every good frame filled)
    ep = write_config(tmp_path / "lacuna.toml", {"floor": {"builtin": "passthrough"}, "walk": {"file": "walk.npz"}},
                      pull=True, osc=True, extra='[streams.good]\nmodel = "walk"\n', daemon={"overdue": "serve"})
    text = open(tmp_path / "lacuna.toml").read().replace("[zmq]\n", "[zmq]\nhwm = 50\n")
    open(tmp_path / "lacuna.toml", "w").write(text)
    d = Daemon(tmp_path / "lacuna.toml", tmp_path / "daemon.log").start()
    S = Sockets()
    good = LockStep(ep["router"], "good", frames)
    try:
        stuck_sub = S.make(zmq.SUB)
        stuck_sub.setsockopt(zmq.RCVHWM, 10)
        stuck_sub.setsockopt(zmq.RCVBUF, 4096)
        stuck_sub.setsockopt(zmq.SUBSCRIBE, b"")
        stuck_sub.connect(ep["pub"])
        stuck_dealer = S.make(zmq.DEALER, ep["router"])  # sends, never reads its answers
        stuck_udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # sends OSC, never reads
        stuck_udp.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stuck_udp.bind(("127.0.0.1", 0))
        push = S.make(zmq.PUSH, ep["pull"])
        wide_join = np.zeros(len(channels), np.float32)
        # the stuck subscriber has joined once it gets a first fill (then it never reads again)
        joins = iter(range(10**6))
        wait_until(lambda: push.send(wire.encode(wire.Frame("join", next(joins), 0.0, wide_join))) or stuck_sub.poll(50),
                   10, "the stuck subscriber's first fill")
        rss0 = d.rss_kib()
        good.start()
        n_flood = 6000
        wide = np.linspace(-90, 90, 1000).astype(np.float32)
        for seq in range(n_flood):
            k = seq % 64
            push.send(wire.encode(wire.Frame(f"flood{k}", seq // 64, 0.0, wide)))
            stuck_dealer.send(wire.encode(wire.Frame(f"dealer{k}", seq // 64, 0.0, wide)))
            if seq % 4 == 0:
                stuck_udp.sendto(fuzzgen.osc_frame(f"osc{k}", seq // 64, 0.0, wide[:400]), ep["osc"])
        def flood_in() -> bool:  # every ZeroMQ frame is in (UDP ones may have been dropped by the kernel)
            st = status(S, ep["router"])
            return st["counters"].get("frames_in", 0) - sum(
                v["frames_in"] for k, v in st["streams"].items() if k == "good") >= 2 * n_flood

        wait_until(flood_in, 60, "the daemon to take in every flooded ZeroMQ frame", interval=0.2)
        n_good = len(good.answers)
        # still serving after the flood, with every consumer stuck
        wait_until(lambda: len(good.answers) > n_good, 10, "an answer to the good stream after the flood")
        good.finish()
        all_filled(good, "walk")

        def settled() -> dict | None:  # frames still in their streams' pending slots are neither served nor dropped yet
            c = status(S, ep["router"])["counters"]
            return c if c["frames_in"] == c["frames_out"] + sum(v for k, v in c.items() if k.startswith("dropped_")) else None

        c = wait_until(settled, 20, "every frame taken in to be served or dropped", interval=0.1)
        dropped = sum(v for k, v in c.items() if k.startswith("dropped_"))
        fills_published = c["frames_out"]
        fills_received = 0
        while stuck_sub.poll(300):
            fills_received += isinstance(wire.decode(stuck_sub.recv_multipart()[1], 1 << 24), wire.FillMsg)
        rss1 = d.rss_kib()
        print(f"\nslow consumers: {fills_published} fills published, the stuck subscriber got {fills_received}; "
              f"frames in {c['frames_in']}, out {c['frames_out']}, dropped (conflated) {dropped}; "
              f"daemon RSS {rss0} -> {rss1} KiB; good stream p50 proc "
              f"{np.median([m.proc_us for m in good.answers.values()]):.0f} us, {len(good.answers)} frames")
        assert fills_received < fills_published  # PUB dropped for the subscriber that did not keep up
        assert c["frames_in"] == c["frames_out"] + dropped, (sorted(c.items()), status(S, ep["router"])["rejected"])
        assert rss1 - rss0 < 64 * 1024  # the stuck peers' backlog is bounded by high-water marks
        stuck_udp.close()
    finally:
        good.stop_flag.set()
        S.close()
        d.stop()


# ---- clock jumps -----------------------------------------------------------------------------------------
def test_timestamp_and_sequence_jumps(tmp_path, walk):
    frames, channels, model = walk
    model.save(str(tmp_path / "walk.npz"))
    ep = write_config(tmp_path / "lacuna.toml", {"walk": {"file": "walk.npz"}}, daemon={"max_gap_frames": 12})
    d = Daemon(tmp_path / "lacuna.toml", tmp_path / "daemon.log").start()
    S = Sockets()
    try:
        s = S.make(zmq.DEALER, ep["router"])
        ts = [100.0, 100.008, 99.0, 99.0, 0.0, -5.0, 1e9, 1e300, -1e300, 1.7e9, 100.0, 5e-324]
        answers, rtt_us = [], []
        for seq, t in enumerate(ts):  # capture clock jumps back, to zero, negative, far forward
            t0 = time.perf_counter()
            s.send(wire.encode(wire.Frame("clock", seq, t, frames[seq])))
            answers.append(recv_msg(s))
            rtt_us.append((time.perf_counter() - t0) * 1e6)
        assert all(isinstance(m, wire.FillMsg) for m in answers), answers
        assert [m.t for m in answers] == ts  # echoed untouched, ordered by seq only
        # proc_us is measured on the daemon's monotonic clock, not from the capture times: it lies
        # inside the round trip that carried it (a bound of the same machine's clocks, not a figure)
        assert all(0 <= m.proc_us <= r for m, r in zip(answers, rtt_us)), [(m.proc_us, r) for m, r in zip(answers, rtt_us)]
        # sequence jumps: a small gap is predicted, a huge one restarts the filter at once
        seq = len(ts) - 1
        for jump in (5, 10**12, 2**62):
            seq += jump
            s.send(wire.encode(wire.Frame("clock", seq, 0.0, frames[seq % len(frames)])))
            m = recv_msg(s)
            assert isinstance(m, wire.FillMsg) and m.seq == seq  # (recv_msg fails the test if no answer comes)
            if jump - 1 <= 12:  # predicted; a longer gap restarts the filter (what `gap` then says is
                assert m.gap == jump - 1  # the daemon's choice: docs/PROTOCOL.md says "frames predicted")
        s.send(wire.encode(wire.Frame("clock", 2**63 - 1, 0.0, frames[0])))  # the largest seq there is
        assert isinstance(recv_msg(s), wire.FillMsg)
        s.send(wire.encode(wire.Frame("clock", 3, 0.0, frames[0])))  # and back to small: late
        m = recv_msg(s)
        assert isinstance(m, wire.Drop) and m.reason == "late"
        st = control(s, "status")["streams"]["clock"]
        assert st["restarts"] == 3 and st["predicted"] == 4 and st["dropped_late"] == 1
        assert st["last_seq"] == 2**63 - 1
        assert d.alive()
    finally:
        S.close()
        d.stop()


def test_broken_config_on_sighup_keeps_the_old_config_serving(tmp_path, walk):
    frames, channels, model = walk
    model.save(str(tmp_path / "walk.npz"))
    cfg = tmp_path / "lacuna.toml"
    ep = write_config(cfg, {"walk": {"file": "walk.npz"}})
    good_text = cfg.read_text()
    d = Daemon(cfg, tmp_path / "daemon.log").start()
    S = Sockets()
    ls = LockStep(ep["router"], "take2", frames)
    breakers = [
        ("UTF-16", lambda: cfg.write_bytes(good_text.encode("utf-16")), "not UTF-8"),
        ("not TOML", lambda: cfg.write_text(good_text + "\n[daemon\n"), "not valid TOML"),
        ("bad value", lambda: cfg.write_text(good_text.replace("budget_ms = 250.0", "budget_ms = -1")), "budget_ms"),
        ("exposed without keys", lambda: cfg.write_text(good_text.replace("[zmq]", "[osc]\nlisten = \"0.0.0.0:9\"\n[zmq]")),
         "osc_allow"),
        ("deleted", lambda: cfg.unlink(), "cannot read"),
    ]
    try:
        ls.start()
        for what, breaker, words in breakers:
            breaker()
            n0 = len(ls.answers)
            d.signal(signal.SIGHUP)
            rec = d.wait_for("reload_done", 15)
            assert rec["ok"] is False, what
            st = status(S, ep["router"])
            assert words in st["reload"]["errors"]["config"], (what, st["reload"])
            wait_until(lambda n0=n0: len(ls.answers) >= n0 + 5, 10, f"5 answers after refusing {what}")
        cfg.write_text(good_text)
        d.signal(signal.SIGHUP)
        assert d.wait_for("reload_done", 15)["ok"] is True
        ls.finish()
        all_filled(ls, "walk")
        assert d.alive()
    finally:
        ls.stop_flag.set()
        S.close()
        d.stop()


def test_passthrough_streams_of_different_widths_batched_together(tmp_path):
    """A pass-through model takes any channel list, so streams of different widths share it;
    frames waiting in the same tick must still each get a fill of their own width (found by
    the slow-consumer test: mixed batches cost every frame of the tick an `internal` error)."""
    ep = write_config(tmp_path / "lacuna.toml", {"floor": {"builtin": "passthrough"}})
    d = Daemon(tmp_path / "lacuna.toml", tmp_path / "daemon.log").start()
    S = Sockets()
    try:
        s = S.make(zmq.DEALER, ep["router"])
        widths = {"narrow": 3, "wide": 1000, "mid": 62}
        for seq in range(40):
            for sid, w in widths.items():  # back to back: read in one drain, served in one tick
                s.send(wire.encode(wire.Frame(sid, seq, 0.0, np.arange(w, dtype=np.float32))))
            for _ in widths:
                m = recv_msg(s)
                assert isinstance(m, wire.FillMsg), m
                assert m.angles.shape == (widths[m.stream],) and m.angles[-1] == widths[m.stream] - 1
        st = control(s, "status")
        assert st["rejected"] == {} and all(st["streams"][k]["frames_out"] == 40 for k in widths)
    finally:
        S.close()
        d.stop()
