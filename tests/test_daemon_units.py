"""Config validation, OSC decoding, sessions and the scheduler's planning, without sockets."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from pythonosc.osc_message_builder import OscMessageBuilder

from daemon import config, osc, wire
from daemon.fillers import PassThroughModel
from daemon.scheduler import CostModel, Scheduler, fill_message, levels_of
from daemon.session import SessionError
from daemon.sessions import SessionTable
from lacuna.filler import Fill
from mocap.baselines import HoldModel

REPO = Path(__file__).resolve().parent.parent
CH = ["a.rx", "b.rx", "c.rx"]


# ---- config -----------------------------------------------------------------------------------
def test_example_config_validates():
    cfg = config.load(str(REPO / "systemd" / "lacuna.toml"))
    assert cfg.default_model in cfg.models and cfg.zmq_router and cfg.budget_ms > 0


@pytest.mark.parametrize("text,needle", [
    ("[daemon]\nbudget_ms = 4\n", "[models] must name at least one model"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[daemon]\nbudget_ms = -1\n", "daemon.budget_ms must be between"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[daemon]\nbudget_ms = \"fast\"\n", "daemon.budget_ms must be"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[daemon]\nbudgt_ms = 3\n", "unknown key daemon.budgt_ms"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[zmqq]\n", "unknown section [zmqq]"),
    ("[models.m]\nbuiltin = \"magic\"\n", "models.m.builtin must be one of"),
    ("[models.m]\nfile = \"a.npz\"\nbuiltin = \"passthrough\"\n", "exactly one of file"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[daemon]\ndefault_model = \"x\"\n", "daemon.default_model 'x' is not under [models]"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[zmq]\nrouter = \"127.0.0.1:5555\"\n", "zmq.router must be a ZeroMQ endpoint"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[zmq]\npull = \"tcp://127.0.0.1:1\"\n", "need zmq.pub"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[osc]\nlisten = \"localhost\"\n", "osc.listen must be \"host:port\""),
    ("[models.m]\nbuiltin = \"passthrough\"\n[streams.s1]\nmodel = \"other\"\n", "streams.s1.model 'other' is not under"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[daemon]\nmax_streams = true\n", "daemon.max_streams must be an integer"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[daemon]\nlog_level = \"loud\"\n", "daemon.log_level must be one of"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[daemon]\noverdue = \"late\"\n", "daemon.overdue must be one of"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[daemon]\nrealtime_priority = 100\n", "daemon.realtime_priority must be between"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[daemon]\nrealtime_priority = 0\n", "daemon.realtime_priority must be between"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[daemon]\nrealtime_priority = 5\nbusy_poll_ms = 1\n", "cannot be used together"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[daemon]\nprewarm_ms = -1\n", "daemon.prewarm_ms must be between"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[daemon]\nprewarm_ms = \"soon\"\n", "daemon.prewarm_ms must be"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[daemon]\nprewarm_spin_ms = -1\n", "daemon.prewarm_spin_ms must be between"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[daemon]\nprewarm_spin_ms = 101\n", "daemon.prewarm_spin_ms must be between"),
    ("[models.m]\nbuiltin = \"passthrough\"\n[daemon]\nprewarm_spin_ms = \"long\"\n", "daemon.prewarm_spin_ms must be"),
    ("models = [", "not valid TOML"),
])
def test_raises_on_bad_config(tmp_path, text, needle):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(config.ConfigError) as ei:
        config.load(str(p))
    assert needle in str(ei.value) and str(p) in str(ei.value)


def test_config_resolves_model_paths_against_its_directory(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text('[models.w]\nfile = "models/w.npz"\n[streams.cam]\nmodel = "w"\n')
    cfg = config.load(str(p))
    assert cfg.models["w"].file == str(tmp_path / "models" / "w.npz")
    assert cfg.stream_models == {"cam": "w"} and cfg.default_model == "w"


def test_config_without_default_model_serves_the_model_named_default(tmp_path):
    """`default` is what streams get unless the config says otherwise (issue 17)."""
    p = tmp_path / "l.toml"
    p.write_text('[models.floor]\nbuiltin = "passthrough"\n[models.default]\nbuiltin = "passthrough"\n')
    assert config.load(str(p)).default_model == "default"
    p.write_text('[models.floor]\nbuiltin = "passthrough"\n[models.other]\nbuiltin = "passthrough"\n')
    assert config.load(str(p)).default_model == "floor"


def test_missing_config_file_names_it(tmp_path):
    with pytest.raises(config.ConfigError, match="nope.toml: cannot read config"):
        config.load(str(tmp_path / "nope.toml"))


def _systemd_analyze() -> str:
    exe = shutil.which("systemd-analyze")
    if exe is None:
        pytest.skip("systemd-analyze is not installed")
    return exe


def _unit_text() -> str:
    """systemd/lacuna.service with ExecStart on this venv's lacuna (verify needs the binary to exist)."""
    lacuna = shutil.which("lacuna") or str(Path(__import__("sys").executable).parent / "lacuna")
    return (REPO / "systemd" / "lacuna.service").read_text().replace("/usr/local/bin/lacuna", lacuna)


def _assert_verifies(exe: str, unit: Path, env: dict[str, str] | None = None) -> None:
    r = subprocess.run([exe, "verify", "--man=no", str(unit)], capture_output=True, text=True, timeout=60, env=env)
    problems = [ln for ln in (r.stdout + r.stderr).splitlines() if "lacuna.service" in ln]
    assert r.returncode == 0 and not problems, r.stdout + r.stderr


def test_systemd_unit_verifies(tmp_path):
    exe = _systemd_analyze()
    (tmp_path / "lacuna.service").write_text(_unit_text())
    _assert_verifies(exe, tmp_path / "lacuna.service")


def test_systemd_unit_verifies_with_its_latency_dropin(tmp_path):
    """systemd/lacuna.service.d/latency.conf (SCHED_RR and the compiled step) parses cleanly on the
    unit, is really applied (the exposure report sees real-time, W^X and @resources allowed), and
    leaves the unit's exposure at or under 2.0 of 10."""
    exe = _systemd_analyze()
    unit = _unit_text()
    (tmp_path / "lacuna.service").write_text(unit)
    (tmp_path / "lacuna.service.d").mkdir()
    shutil.copy(REPO / "systemd" / "lacuna.service.d" / "latency.conf", tmp_path / "lacuna.service.d")
    # drop-ins are found beside the unit
    _assert_verifies(exe, tmp_path / "lacuna.service", {**os.environ, "SYSTEMD_UNIT_PATH": f"{tmp_path}:"})

    (tmp_path / "plain").mkdir()  # the unit alone, in a directory without the drop-in
    (tmp_path / "plain" / "lacuna.service").write_text(unit)

    def relaxed(d: Path) -> set[str]:
        r = subprocess.run([exe, "security", "--offline=true", "--threshold=20", "--json=short",
                            str(d / "lacuna.service")], capture_output=True, text=True, timeout=60,
                           env={**os.environ, "SYSTEMD_UNIT_PATH": f"{d}:"})
        assert r.returncode == 0, r.stdout[-500:] + r.stderr  # exposure <= 2.0
        return {x["json_field"] for x in json.loads(r.stdout) if x["set"] is False}

    gained = relaxed(tmp_path) - relaxed(tmp_path / "plain")
    assert gained == {"RestrictRealtime", "MemoryDenyWriteExecute", "SystemCallFilter_resources"}, gained


# ---- OSC decode -------------------------------------------------------------------------------
def _osc(addr, *args):
    b = OscMessageBuilder(addr)
    for v, t in args:
        b.add_arg(v, t)
    return b.build().dgram


OSC_FRAME_S1_SEQ7_T1_5_10_NAN = bytes.fromhex(
    "2f6c6163756e612f6672616d650000002c7369646666000073310000000000073ff80000000000004120000"
    "07fc00000")


def test_osc_protocol_example_frame():
    m = osc.decode(OSC_FRAME_S1_SEQ7_T1_5_10_NAN)
    assert isinstance(m, wire.Frame) and (m.stream, m.seq, m.t) == ("s1", 7, 1.5)
    assert m.angles[0] == 10.0 and np.isnan(m.angles[1])


def test_osc_masked_frame_and_hello_and_reset():
    ang = np.array([1.0, 0.0], "<f4").tobytes()
    m = osc.decode(_osc("/lacuna/frame/masked", ("s", "s"), (3, "h"), (0.5, "f"), (ang, "b"), (b"\x01\x00", "b")))
    assert m.observed.tolist() == [True, False]
    h = osc.decode(_osc("/lacuna/hello", ("s", "s"), ("", "s"), ("x.rx", "s"), ("y.rx", "s")))
    assert h == wire.Hello("s", ["x.rx", "y.rx"], None)
    assert osc.decode(_osc("/lacuna/reset", ("s", "s"))) == wire.Control("reset", "s")


@pytest.mark.parametrize("data,reason", [
    (b"garbage", "not_osc"),
    (b"/lacuna/frame\x00\x00\x00,s", "not_osc"),
    (_osc("/other", (1, "i")), "unknown_type"),
    (_osc("/lacuna/frame", ("s", "s"), ("x", "s"), (0.0, "d"), (1.0, "f")), "bad_type"),
    (_osc("/lacuna/frame", ("s", "s"), (1, "i"), (0.0, "d")), "bad_type"),
    (_osc("/lacuna/frame", ("s", "s"), (1, "i"), (0.0, "d"), (float("inf"), "f")), "non_finite"),
    (_osc("/lacuna/frame", ("s", "s"), (-1, "i"), (0.0, "d"), (1.0, "f")), "bad_seq"),
    (_osc("/lacuna/hello", ("s", "s"), ("", "s")), "bad_length"),
    (_osc("/lacuna/hello", ("s", "s"), ("", "s"), (3, "i")), "bad_type"),
    (_osc("/lacuna/frame/masked", ("s", "s"), (1, "i"), (0.0, "d"), (b"\0\0", "b"), (b"\1", "b")), "bad_length"),
    (b"/x" + b"\0" * 200, "too_large"),
])
def test_osc_raises_on_bad_datagram(data, reason):
    with pytest.raises(wire.WireError) as ei:
        osc.decode(data, max_bytes=150)
    assert ei.value.reason == reason, ei.value.detail


def _bundle(*elements: bytes, tt: bytes = b"\x00" * 7 + b"\x01") -> bytes:
    """An OSC bundle by hand: #bundle, timetag, then (int32 size, element) each."""
    return osc.BUNDLE_PREFIX + tt + b"".join(len(e).to_bytes(4, "big") + e for e in elements)


def _fr(sid, seq, *vals):
    return _osc("/lacuna/frame", (sid, "s"), (seq, "i"), (0.5, "d"), *[(v, "f") for v in vals])


def test_osc_bundle_gives_each_message_and_a_malformed_one_costs_only_itself():
    hello = _osc("/lacuna/hello", ("p2", "s"), ("", "s"), ("x.rx", "s"), ("y.rx", "s"))
    inner = _bundle(_fr("p3", 1, 5.0, 6.0))
    items = osc.decode_bundle(_bundle(_fr("p1", 7, 1.0, float("nan")), hello, _osc("/other", (1, "i")),
                                      _fr("p2", 7, 3.0, 4.0), inner, _osc("/lacuna/reset", ("p1", "s"))))
    kinds = [type(m).__name__ for m in items]
    assert kinds == ["Frame", "Hello", "WireError", "Frame", "Frame", "Control"]
    assert (items[0].stream, items[0].seq) == ("p1", 7) and np.isnan(items[0].angles[1])
    assert items[2].reason == "unknown_type" and items[4].stream == "p3" and items[5] == wire.Control("reset", "p1")
    # the same bytes as python-osc would build (timetag "immediately")
    from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
    from pythonosc.osc_message import OscMessage

    bb = OscBundleBuilder(IMMEDIATELY)
    bb.add_content(OscMessage(_fr("p1", 7, 1.0, 2.0)))
    assert bb.build().dgram == _bundle(_fr("p1", 7, 1.0, 2.0))
    assert [m.seq for m in osc.decode_bundle(bb.build().dgram)] == [7]
    assert osc.decode_bundle(_bundle()) == []  # an empty bundle is valid OSC: nothing to answer


def test_osc_bundle_structure_errors():
    good = _fr("p1", 7, 1.0, 2.0)
    # an element that declares more bytes than are left: what came before is kept, one error for the rest
    bad_size = osc.BUNDLE_PREFIX + b"\0" * 8 + len(good).to_bytes(4, "big") + good + (999).to_bytes(4, "big") + good
    items = osc.decode_bundle(bad_size)
    assert isinstance(items[0], wire.Frame) and len(items) == 2 and items[1].reason == "malformed"
    assert "cannot be read" in items[1].detail
    # nested too deep: that element is an error, its neighbours are served
    deep = good
    for _ in range(osc.MAX_DEPTH + 1):
        deep = _bundle(deep)
    items = osc.decode_bundle(_bundle(good, deep))
    assert isinstance(items[0], wire.Frame) and items[1].reason == "malformed" and "nested" in items[1].detail
    with pytest.raises(wire.WireError) as ei:  # more messages than a bundle may carry
        osc.decode_bundle(_bundle(*[good] * (wire.MAX_BUNDLE + 1)), max_bytes=1 << 20)
    assert ei.value.reason == "too_large"
    with pytest.raises(wire.WireError) as ei:  # the same, hidden in a nested bundle
        osc.decode_bundle(_bundle(good, _bundle(*[good] * wire.MAX_BUNDLE)), max_bytes=1 << 20)
    assert ei.value.reason == "too_large"
    for data, reason in ((b"#bundle\x00\x00", "not_osc"), (good, "not_osc"), (_bundle(good) + b"\0" * 200, "too_large")):
        with pytest.raises(wire.WireError) as ei:
            osc.decode_bundle(data, max_bytes=150)
        assert ei.value.reason == reason
    items = osc.decode_bundle(_bundle(good) + b"\0\0")  # stray bytes after the last element
    assert isinstance(items[0], wire.Frame) and items[1].reason == "malformed"
    # osc.decode (one message) names a bundle for what it is
    with pytest.raises(wire.WireError) as ei:
        osc.decode(_bundle(good))
    assert "bundle" in ei.value.detail


# ---- sessions ---------------------------------------------------------------------------------
def _table(model, max_streams=4):
    counted = []
    t = SessionTable(lambda req, sid: ("m", model), max_streams, lambda name, sid: counted.append(name))
    return t, counted


def _frame(sid, seq, vals, observed=None):
    return wire.Frame(sid, seq, 0.0, np.asarray(vals, np.float32), observed)


def test_session_conflation_keeps_newest_and_answers_the_rest():
    t, counted = _table(HoldModel(CH, np.zeros(3), np.ones(3)))
    assert t.frame(_frame("s", 0, [1, 2, 3]), ("router", ["a"]), 0.0) == []
    out = t.frame(_frame("s", 1, [1, 2, 3]), ("router", ["b"]), 0.0)
    assert out == [(("router", ["a"]), wire.Drop("s", 0, "conflated"))]
    out = t.frame(_frame("s", 1, [1, 2, 3]), ("router", ["c"]), 0.0)
    assert out == [(("router", ["c"]), wire.Drop("s", 1, "duplicate"))]
    assert t.sessions["s"].pending.frame.seq == 1 and counted == ["dropped_conflated", "dropped_duplicate"]


def test_session_limit_and_width():
    t, _ = _table(HoldModel(CH, np.zeros(3), np.ones(3)), max_streams=2)
    t.frame(_frame("a", 0, [1, 2, 3]), ("pull", None), 0.0)
    t.frame(_frame("b", 0, [1, 2, 3]), ("pull", None), 0.0)
    with pytest.raises(SessionError) as ei:
        t.frame(_frame("c", 0, [1, 2, 3]), ("pull", None), 0.0)
    assert ei.value.reason == "too_many_streams"
    with pytest.raises(SessionError) as ei:
        t.frame(_frame("a", 1, [1, 2]), ("pull", None), 0.0)
    assert ei.value.reason == "width"


def test_observed_mask_wins_over_values_and_passthrough_channels_untouched():
    model = HoldModel(CH, np.array([5.0, 6.0, 7.0]), np.ones(3))
    t, _ = _table(model)
    t.hello(wire.Hello("s", ["c.rx", "zz", "a.rx"]))
    # a.rx carries a number but is marked unobserved: the model must fill it
    t.frame(_frame("s", 0, [1.0, 42.0, 9.0], np.array([1, 0, 0], bool)), ("pull", None), 0.0)
    sched = Scheduler(100.0, 5, 64)
    s = t.sessions["s"]
    [(sess, fill, status)] = sched.run({id(model): (model, [s])}, 0.0)
    msg = fill_message(sess, fill, status, 0.001)
    # zz (passed through) was masked out: NaN, not the 42 sent under the mask (docs/PROTOCOL.md, issue 18 F5)
    assert msg.angles[0] == 1.0 and np.isnan(msg.angles[1]) and msg.angles[2] == 5.0
    assert msg.filled.tolist() == [False, False, True] and msg.status == "ok"


# ---- scheduler --------------------------------------------------------------------------------
def test_cost_model_recovers_affine_cost():
    cm = CostModel()
    for n in [1, 4, 16, 64, 8, 2] * 5:
        cm.observe(n, 1e-4 + 2e-5 * n)
    a, b = cm.coef()
    assert a == pytest.approx(1e-4, rel=1e-6) and b == pytest.approx(2e-5, rel=1e-6)
    cm2 = CostModel()
    for _ in range(5):
        cm2.observe(8, 8e-4)  # one batch size only: cost taken as proportional to n
    assert cm2.estimate(16) == pytest.approx(1.25 * 16e-4)


class KnobModel(HoldModel):
    """A hold model with CRBM-style levels (K, K/2, ..., 1 Gibbs iterations), to test planning."""

    def __init__(self, *a, k=30):
        super().__init__(*a)
        self.n_gibbs = k
        self.calls: list[int] = []

    def quality_levels(self):
        out, v = [self.n_gibbs], self.n_gibbs
        while v > 1:
            v = max(1, v // 2)
            out.append(v)
        return out

    def step_batch(self, states, frames, observed, level=None):
        self.calls.append(self.n_gibbs if level is None else level)
        return super().step_batch(states, frames, observed)


def test_levels_and_plan_degrades_iterations_then_holds():
    m = KnobModel(CH, np.zeros(3), np.ones(3))
    assert levels_of(m) == [30, 15, 7, 3, 1]
    assert levels_of(HoldModel(CH, np.zeros(3), np.ones(3))) == [None]
    t, _ = _table(m, max_streams=100)
    for i in range(10):
        t.frame(_frame(f"s{i}", 0, [1.0, np.nan, 3.0]), ("pull", None), 0.0)
    group = list(t.sessions.values())
    sched = Scheduler(budget_ms=1.0, max_gap=5, max_batch=64)
    sched.reply_cost = 0.0
    sched.hold_cost.observe(10, 20e-6)  # holding: 2 us a stream
    # cost per stream: 1 ms at K=30 ... proportional to K
    for lv in levels_of(m):
        for _ in range(3):
            sched.cost(m, lv).observe(1, 1e-3 * lv / 30)
            sched.cost(m, lv).observe(10, 1e-2 * lv / 30)
    plan = sched.plan(m, group, now=0.0)  # 10 streams: K=30 would cost 12.5 ms, K=3 1.25 ms, K=1 0.42 ms
    assert plan.iterations == 1 and plan.degraded and not plan.hold
    sched.budget_s = 0.23e-3
    plan = sched.plan(m, group, now=0.0)  # even K=1 is too slow for all ten: five step, five hold
    assert plan.iterations == 1 and plan.degraded and len(plan.step) == 5 and len(plan.hold) == 5
    sched.budget_s = 1.0
    plan = sched.plan(m, group, now=0.0)
    assert plan.iterations == 30 and not plan.degraded and len(plan.step) == 10
    # a degraded step is given its level as an argument; the model is left as it was
    sched.budget_s = 1e-3
    for s in group:
        s.pending.arrived = time.perf_counter()
    res = sched.run({id(m): (m, group)}, 0.0)
    assert m.n_gibbs == 30 and all(st == "degraded" for _, _, st in res) and len(res) == 10
    assert m.calls and set(m.calls) <= {1, 3}


def test_rehandshake_or_reset_answers_the_waiting_frame():
    t, counted = _table(HoldModel(CH, np.zeros(3), np.ones(3)))
    t.frame(_frame("s", 5, [1, 2, 3]), ("router", ["a"]), 0.0)
    ack, out = t.hello(wire.Hello("s", ["a.rx", "b.rx"]))
    assert ack.channels == ["a.rx", "b.rx"]
    assert out == [(("router", ["a"]), wire.Drop("s", 5, "reset"))]
    t.frame(_frame("s", 6, [1, 2]), ("router", ["b"]), 0.0)
    ok, out = t.reset("s")
    assert ok and out == [(("router", ["b"]), wire.Drop("s", 6, "reset"))] and "s" not in t.sessions
    assert counted == ["dropped_reset", "dropped_reset"]
    assert t.reset("s") == (False, [])


def test_passthrough_filler_fills_nothing():
    m = PassThroughModel(CH)
    st = m.stream()
    f = st.step(np.array([1.0, np.nan, 3.0]))
    assert np.isnan(f.frame[1]) and f.frame[0] == 1.0 and not f.filled.any() and not f.std.any()
    assert np.isnan(st.predict().frame).all()
    fills = m.step_batch([st, m.stream()], np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]), np.array([[1, 0, 1], [1, 1, 1]], bool))
    assert np.isnan(fills[0].frame[1]) and fills[1].frame.tolist() == [4.0, 5.0, 6.0]
    assert PassThroughModel().stream().step(np.ones(5)).frame.tolist() == [1.0] * 5  # "any" channels


def test_model_held_everywhere_still_gets_a_probe_step():
    """A pessimistic estimate must not hold every stream forever: one real step per PROBE_S."""
    m = HoldModel(CH, np.zeros(3), np.ones(3))
    t, _ = _table(m, max_streams=100)
    sched = Scheduler(budget_ms=1.0, max_gap=5, max_batch=64)
    for _ in range(3):
        sched.cost(m, None).observe(1, 10.0)  # "10 s per step": far over any budget

    def tick(seq):
        for i in range(4):
            t.frame(_frame(f"s{i}", seq, [1.0, np.nan, 3.0]), ("pull", None), time.perf_counter())
        return sched.run({id(m): (m, list(t.sessions.values()))}, 0.0)

    first = tick(0)
    assert sum(not f.degraded for _, f, _ in first) == 1 and sched.probes == 1  # one stream stepped
    second = tick(1)
    assert all(f.degraded for _, f, _ in second) and sched.probes == 1  # not again within PROBE_S
    stepped = next(s for s, f, _ in first if not f.degraded)
    assert stepped.model_seq == 1 and stepped.held_streak == 1  # its held frame 1 is skipped, not replayed


def test_partial_step_without_knob_is_full_quality_not_degraded():
    m = HoldModel(CH, np.zeros(3), np.ones(3))
    t, _ = _table(m, max_streams=100)
    for i in range(10):
        t.frame(_frame(f"s{i}", 0, [1.0, np.nan, 3.0]), ("pull", None), 0.0)
    sched = Scheduler(budget_ms=0.23, max_gap=5, max_batch=64)
    sched.reply_cost = 0.0
    sched.hold_cost.observe(10, 20e-6)  # holding: 2 us a stream
    for _ in range(3):
        sched.cost(m, None).observe(1, 1e-3 / 30)
        sched.cost(m, None).observe(10, 1e-2 / 30)
    plan = sched.plan(m, list(t.sessions.values()), now=0.0)
    # 5 steps at 41.7 us (1.25 x 33.3) and 5 holds at 2.5 us fit in 230 us
    assert len(plan.step) == 5 and len(plan.hold) == 5 and not plan.degraded
    # the streams held cost time too: at 10 us a hold, only 3 step (3 x 41.7 + 7 x 12.5 = 212 us)
    sched.hold_cost = CostModel()
    sched.hold_cost.observe(10, 100e-6)
    plan = sched.plan(m, list(t.sessions.values()), now=0.0)
    assert len(plan.step) == 3 and len(plan.hold) == 7


def test_tick_inputs_and_replies_built_as_arrays_equal_the_row_by_row_ones():
    """model_inputs / fill_messages stack a tick of identity-mapped streams into (n, C) arrays
    (from STACK_MIN streams on); the result must be the per-stream to_model / fill_message's,
    whatever mix of masks, NaN and remapped streams the tick holds."""
    from daemon.scheduler import STACK_MIN, fill_messages, model_inputs

    model = HoldModel(CH, np.array([5.0, 6.0, 7.0]), np.ones(3))
    t, _ = _table(model, max_streams=64)
    rng = np.random.default_rng(0)
    n = STACK_MIN + 3
    for i in range(n):
        vals = rng.normal(size=3)
        if i % 3 == 0:
            vals[1] = np.nan                                   # missing by NaN
        mask = np.array([1, 0, 1], bool) if i % 3 == 1 else None  # missing by mask (value sent anyway)
        t.frame(_frame(f"s{i}", 0, vals, mask), ("pull", None), 0.0)
    t.hello(wire.Hello("remap", ["c.rx", "zz", "a.rx"]))       # a remapped stream rides along
    t.frame(_frame("remap", 0, [1.0, 42.0, np.nan]), ("pull", None), 0.0)
    group = [s for sid, s in t.sessions.items() if sid != "remap"]
    mf, mo = model_inputs(group, 3)
    for i, s in enumerate(group):
        f1, o1 = s.to_model(s.pending.frame)
        assert np.array_equal(mf[i], f1, equal_nan=True) and np.array_equal(mo[i], o1)
    sched = Scheduler(100.0, 5, 64)
    results = sched.run({id(model): (model, list(t.sessions.values()))}, 0.0)
    assert len(results) == n + 1
    batch = fill_messages(results, 0.001)
    for (s, fill, status), got in zip(results, batch):
        want = fill_message(s, fill, status, 0.001)
        assert isinstance(got, wire.FillMsg)
        assert wire.encode(got) == wire.encode(want), s.sid
    # a fill the wire cannot carry fails its own stream only
    bad = [(s, Fill(np.zeros(5), np.zeros(5), np.zeros(5, bool)) if i == 2 else f, st)
           for i, (s, f, st) in enumerate(results)]
    out = fill_messages(bad, 0.001)
    assert isinstance(out[2], Exception)
    assert all(isinstance(m, wire.FillMsg) for i, m in enumerate(out) if i != 2)


# ---- a burst's superseded frames, answered after the step (server.Daemon._batch) ---------------
class FakeClock:
    """The daemon's clock in a test (``Daemon(cfg, clock=...)``): it moves only when told."""

    def __init__(self, t: float = 1000.0):
        self.t = t

    def __call__(self) -> float:
        return self.t

    def advance(self, s: float) -> None:
        self.t += s


class _Recording:
    """server.Daemon whose answers are kept in order instead of sent (the burst logic is tested
    here, in process, against in-order handling; tests/test_daemon_e2e.py has it over sockets)."""

    @staticmethod
    def make(batch_min: int, budget_ms: float = 100.0, overdue: str = "serve", clock=time.perf_counter,
             idle_timeout_s: float = 30.0):
        # (these tests give frames made-up receipt times: "serve" keeps the overdue check, which
        # reads the clock, out of them; the overdue tests below pass "drop")
        from daemon import dispatch, server

        class D(server.Daemon):
            def _send(self, origin, msg, publish=False):
                self.sent.append((origin, msg))

            def _batch(self, items):
                old, dispatch.BATCH_MIN = dispatch.BATCH_MIN, batch_min
                try:
                    super()._batch(items)
                finally:
                    dispatch.BATCH_MIN = old

        cfg = config.from_dict({"daemon": {"budget_ms": budget_ms, "max_streams": 8, "log_level": "error", "overdue": overdue,
                                           "idle_timeout_s": idle_timeout_s},
                                "models": {"pt": {"builtin": "passthrough"}}, "zmq": {"router": "tcp://127.0.0.1:*"}})
        d = D(cfg, server.Log("error"), clock=clock)
        d.sent = []
        from daemon.models import load_all

        table, errors = load_all(cfg)
        assert not errors
        d._install(table)
        return d


def _answers(d) -> list[tuple]:
    out = []
    for origin, m in d.sent:
        if isinstance(m, wire.FillMsg):
            out.append(("fill", origin[1], m.stream, m.seq, m.status, m.angles.tobytes(), m.gap))
        elif isinstance(m, wire.Drop):
            out.append(("drop", origin[1], m.stream, m.seq, m.reason))
        elif isinstance(m, wire.ErrorMsg):
            out.append(("error", origin[1], m.stream, m.seq, m.reason))
        else:
            out.append((type(m).__name__, origin[1], getattr(m, "stream", None)))
    return sorted(out, key=repr)


def _turn(d, items) -> int:
    """One loop turn (the loop's own Daemon.turn); returns how many frames were set aside."""
    return d.turn(d.clock(), items=items)


def _burst(rng, C: int, turn: int, clock=time.perf_counter) -> list[tuple[bytes, tuple, float]]:
    """Frames of streams a, b (open) and c (sometimes new), in and out of order, duplicates,
    some malformed (wrong width, infinity, not msgpack, bad seq), now and then a hello."""
    items = []
    seqs = {"a": 100 * turn, "b": 100 * turn, "c": 100 * turn}
    for _k in range(int(rng.integers(3, 40))):
        sid = str(rng.choice(["a", "a", "b", "c"]))
        seqs[sid] += int(rng.choice([1, 1, 1, 2, 0, -1, -3]))
        vals = rng.normal(size=C).astype(np.float32)
        r = rng.random()
        if r < 0.05:
            data = b"\x93not a map"
        elif r < 0.10:
            data = wire.encode(wire.Frame(sid, seqs[sid], 0.0, np.ones(C + 1, np.float32)))
        elif r < 0.15:
            vals[0] = np.inf
            data = wire.encode(wire.Frame(sid, seqs[sid], 0.0, vals))
        elif r < 0.165:
            data = wire.encode(wire.Hello(sid, [f"ch{i}" for i in range(C)]))
        elif r < 0.21:
            m = wire.to_map(wire.Frame(sid, max(seqs[sid], 0), 0.0, vals))
            m["seq"] = -5
            import msgpack

            data = msgpack.packb(m, use_bin_type=True)
        else:
            vals[rng.random(C) < 0.3] = np.nan
            data = wire.encode(wire.Frame(sid, max(seqs[sid], 0), 0.0, vals))
        # (fresh: none is late; each stream from its own peer, which owns it: docs/PROTOCOL.md)
        items.append((data, ("router", [f"peer-{sid}".encode()]), clock()))
    return items


@pytest.mark.parametrize("seed", range(12))
def test_burst_answers_equal_in_order_handling(seed):
    """Setting superseded frames aside changes when they are answered, never what: every answer,
    session counter and global counter equals handling each message in arrival order."""
    rng = np.random.default_rng(seed)
    C = 5
    # (one fake clock for both: a turn takes no time, so no frame is late, over budget or served
    # early in a slice however loaded the machine is; the clock moves a frame period a turn)
    clock = FakeClock()
    fast, ref = _Recording.make(3, clock=clock), _Recording.make(10**9, clock=clock)
    for d in (fast, ref):
        for sid in ("a", "b"):
            d.sessions.hello(wire.Hello(sid, [f"ch{i}" for i in range(C)]), ("conn", f"peer-{sid}".encode()))
    set_aside = 0
    for turn in range(10):
        clock.advance(1 / 120)
        items = _burst(rng, C, turn, clock)
        fast.sent.clear()
        ref.sent.clear()
        set_aside += _turn(fast, list(items))
        assert _turn(ref, list(items)) == 0
        assert _answers(fast) == _answers(ref), f"turn {turn}"
        assert fast.metrics.counters == ref.metrics.counters and fast.metrics.rejected == ref.metrics.rejected
        assert {k: s.counts for k, s in fast.sessions.sessions.items()} == \
            {k: s.counts for k, s in ref.sessions.sessions.items()}
        assert {k: s.last_seq for k, s in fast.sessions.sessions.items()} == \
            {k: s.last_seq for k, s in ref.sessions.sessions.items()}
    assert set_aside > 0  # the bursts did exercise the set-aside path


def test_burst_sets_superseded_frames_aside_until_the_fills_are_out():
    """A burst of one open stream: only the newest frame is decoded and served before the step;
    the older ones are answered `conflated` after its fill, in their own order."""
    C = 4
    d = _Recording.make(3)
    d.sessions.hello(wire.Hello("a", [f"ch{i}" for i in range(C)]))
    items = [(wire.encode(wire.Frame("a", s, 0.0, np.full(C, s, np.float32))), ("router", [b"p"]), float(s))
             for s in range(10)]
    d._batch(items)
    # (the chain: the nine kept as one run of heads, daemon/aside.py, and None for the served one)
    assert [[len(x) if type(x) is list else x for x in c] for *_, c in d._superseded] == [[9, None]]
    assert d.sessions.sessions["a"].pending.frame.seq == 9
    d._serve()
    assert [type(m).__name__ for _, m in d.sent] == ["FillMsg"] and d.sent[0][1].seq == 9
    d._answer_superseded()
    assert [(type(m).__name__, m.seq, m.reason) for _, m in d.sent[1:]] == [("Drop", s, "conflated") for s in range(9)]
    s = d.sessions.sessions["a"]
    assert s.counts["dropped_conflated"] == 9 and s.counts["frames_in"] == 10 and s.last_seq == 9 and s.pending is None
    # a new stream, or a hello in the burst: nothing is set aside (handled in order)
    d.sent.clear()
    items = [(wire.encode(wire.Frame("new", s, 0.0, np.zeros(C, np.float32))), ("router", [b"p"]), 0.0) for s in range(5)]
    d._batch(items)
    assert d._superseded == [] and d.sent == []
    # (handled in order: each older frame was conflated as the next came; those drops, too,
    # wait for the turn's fills)
    assert [(m.seq, m.reason) for _, m in d._conflated] == [(s, "conflated") for s in range(4)]
    d._serve()
    d._answer_superseded()
    assert [m.seq for _, m in d.sent] == [4, 0, 1, 2, 3] and d._conflated == []
    items = [(wire.encode(wire.Frame("a", s, 0.0, np.zeros(C, np.float32))), ("router", [b"p"]), 0.0) for s in (10, 11)]
    items.insert(1, (wire.encode(wire.Hello("b", [f"ch{i}" for i in range(C)])), ("router", [b"p"]), 0.0))
    items.append((wire.encode(wire.Frame("a", 12, 0.0, np.zeros(C, np.float32))), ("router", [b"p"]), 0.0))
    d._batch(items)
    assert d._superseded == []
    # nor when an OSC datagram came in the same turn (a hello over OSC could replace the session)
    d._serve()
    d._answer_superseded()
    items = [(wire.encode(wire.Frame("a", s, 0.0, np.zeros(C, np.float32))), ("router", [b"p"]), 0.0) for s in (20, 21, 22)]
    items.append((_osc("/lacuna/hello", ("a", "s"), ("", "s"), *[(f"ch{i}", "s") for i in range(C)]), ("osc", ("127.0.0.1", 9)), 0.0))
    d._batch(items)
    # (nothing set aside; the OSC sender does not own "a", so its hello is refused and 22 waits)
    assert d._superseded == [] and d.sessions.sessions["a"].pending.frame.seq == 22
    assert [m.reason for _, m in d.sent if isinstance(m, wire.ErrorMsg)] == ["not_owner"]


def test_hold_of_a_group_as_arrays_equals_holding_stream_by_stream():
    """Scheduler._hold_many stacks a group's held streams; each must get what _hold gives it
    alone: observed values as sent, the rest from its last output (NaN std), state advanced."""
    from daemon.scheduler import STACK_MIN

    model = HoldModel(CH, np.array([5.0, 6.0, 7.0]), np.ones(3))
    rng = np.random.default_rng(3)
    tables = [_table(model, max_streams=64)[0] for _ in range(2)]
    n = STACK_MIN + 4
    for t in tables:
        t.hello(wire.Hello("remap", ["c.rx", "zz", "a.rx"]))
    for i in range(n):
        vals = rng.normal(size=3)
        last = rng.normal(size=3)
        if i % 4 == 0:
            vals[1] = np.nan
        if i % 5 == 0:
            last[2] = np.nan  # nothing to hold for that channel
        mask = np.array([1, 0, 1], bool) if i % 3 == 1 else None
        for t in tables:
            t.frame(_frame(f"s{i}", 7, vals, mask), ("pull", None), 0.0)
            s = t.sessions[f"s{i}"]
            s.last_out, s.model_seq = last.copy(), 3
    for t in tables:
        t.frame(_frame("remap", 7, [1.0, 42.0, np.nan]), ("pull", None), 0.0)
        t.sessions["remap"].last_out, t.sessions["remap"].model_seq = np.array([9.0, 8.0, 7.0]), 3
    sched = Scheduler(100.0, 5, 64)
    many = sched._hold_many(list(tables[0].sessions.values()))
    one = [sched._hold(s) for s in tables[1].sessions.values()]
    assert len(many) == len(one) == n + 1
    for (s1, f1, st1), (s2, f2, st2) in zip(many, one):
        assert s1.sid == s2.sid and st1 == st2 == "degraded" and f1.degraded and f2.degraded
        for a, b in ((f1.frame, f2.frame), (f1.std, f2.std), (f1.filled, f2.filled), (s1.last_out, s2.last_out)):
            assert np.array_equal(a, b, equal_nan=True), s1.sid
        assert (s1.model_seq, s1.held_streak, s1.counts["held"]) == (s2.model_seq, s2.held_streak, s2.counts["held"]) == (7, 1, 1)


def test_a_tick_answers_its_frames_oldest_first():
    """Replies are a few dozen microseconds each: the frame that arrived first, nearest its
    budget, is answered first whatever the order of the streams in the session table."""
    d = _Recording.make(3)
    C = 3
    for sid, arrived in (("late", 5.0), ("early", 1.0), ("mid", 3.0), ("latest", 7.0)):
        d.sessions.hello(wire.Hello(sid, [f"ch{i}" for i in range(C)]))
        d.sessions.frame(wire.Frame(sid, 0, 0.0, np.zeros(C, np.float32)), ("router", [sid.encode()]), arrived)
    d._serve()
    assert [m.stream for _, m in d.sent] == ["early", "mid", "late", "latest"]
    assert all(isinstance(m, wire.FillMsg) for _, m in d.sent)


# ---- frames the daemon cannot answer within its budget (daemon.overdue) ------------------------
def test_overdue_marks_only_the_frames_that_cannot_make_their_deadline():
    """Oldest first, each frame at its place in the reply order, at no cost but the sends before
    it; a frame marked frees its place for the next."""
    sched = Scheduler(budget_ms=4.0, max_gap=5, max_batch=64)
    sched.encode_cost, sched.send_cost = 50e-6, 100e-6
    now = 100.0
    assert sched.overdue([now - 1e-3, now, now - 2e-3], now) == [False] * 3  # plenty of time
    ages = [3.95e-3, 3.85e-3, 3.6e-3, 0.0]
    # 3.95 + 0.1 > 4: marked; 3.85 + 0.1 at place 1: in time; 3.6 + 0.2: in time (encoding is not counted)
    assert sched.overdue([now - a for a in ages], now) == [True, False, False, False]
    sched.send_cost = 200e-6  # 3.85 + 0.2 at place 1 is now too late as well
    assert sched.overdue([now - a for a in ages], now) == [True, True, False, False]
    assert sched.sent_at(now, 3, 2) == pytest.approx(now + 3 * 50e-6 + 2 * 200e-6)


def test_reply_cost_estimates_shrug_off_one_stretched_send():
    """One send held up by the OS for 5 ms moves the estimate by a bounded step, and every turn
    that sends anything refreshes it."""
    sched = Scheduler(budget_ms=4.0, max_gap=5, max_batch=64)
    sched.send_cost = 20e-6
    sched.observe_sends(1, 5e-3)
    assert sched.send_cost == pytest.approx(0.9 * 20e-6 + 0.1 * 80e-6)
    for _ in range(60):
        sched.observe_sends(64, 64 * 10e-6)
    assert sched.send_cost == pytest.approx(10e-6, rel=0.05)
    sched.encode_cost = sched.reply_cost = 10e-6
    sched.observe_replies(64, 64 * 5e-6, 64 * 15e-6)
    assert sched.encode_cost == pytest.approx(0.9 * 10e-6 + 0.1 * 5e-6)
    assert sched.reply_cost == pytest.approx(0.9 * 10e-6 + 0.1 * 15e-6)


def _overdue_daemon(overdue: str, budget_ms: float = 50.0, clock=time.perf_counter):
    d = _Recording.make(3, budget_ms=budget_ms, overdue=overdue, clock=clock)
    d.sessions.hello(wire.Hello("a", ["ch0", "ch1", "ch2"]))
    return d


def _send_frame(d, seq: int, arrived: float) -> None:
    d._batch([(wire.encode(wire.Frame("a", seq, seq / 120, np.full(3, float(seq), np.float32))), ("router", [b"p"]), arrived)])


def test_a_frame_too_old_to_answer_in_budget_is_dropped_overdue_after_the_fills():
    d = _overdue_daemon("drop")
    _send_frame(d, 0, time.perf_counter())
    d._serve()
    assert [type(m).__name__ for _, m in d.sent] == ["FillMsg"]
    d.sent.clear()
    _send_frame(d, 1, time.perf_counter() - 0.06)  # read 60 ms ago: over the 50 ms budget already
    d._serve()
    assert d.sent == []  # nothing is sent before the turn's fills
    d._answer_superseded()
    assert [(type(m).__name__, m.seq, m.reason) for _, m in d.sent] == [("Drop", 1, "overdue")]
    s = d.sessions.sessions["a"]
    assert s.counts["dropped_overdue"] == 1 and s.info()["dropped"] == 1 and s.counts["frames_out"] == 1
    assert d.metrics.counters["dropped_overdue"] == 1 and s.pending is None and s.last_seq == 1
    # the frame counts as answered: sent again it is a duplicate; the next one is served
    d.sent.clear()
    _send_frame(d, 1, time.perf_counter())
    _send_frame(d, 2, time.perf_counter())
    d._serve()
    assert [(type(m).__name__, m.seq) for _, m in d.sent] == [("Drop", 1), ("FillMsg", 2)]
    assert d.sent[0][1].reason == "duplicate" and d.sent[1][1].status == "passthrough"
    # with overdue = "serve" the same frame is filled, late, and counted over budget
    d = _overdue_daemon("serve")
    _send_frame(d, 0, time.perf_counter() - 0.06)
    d._serve()
    d._answer_superseded()
    assert [type(m).__name__ for _, m in d.sent] == ["FillMsg"] and d.sent[0][1].proc_us > 60000
    s = d.sessions.sessions["a"]
    assert s.counts["dropped_overdue"] == 0 and s.counts["over_budget"] == 1 and d.metrics.counters["over_budget"] == 1


def test_a_step_that_overruns_turns_its_fill_into_an_overdue_drop():
    """The plan thought the step fitted (its cost estimate says so), the step then took three
    budgets (as when the OS takes the CPU away): the fill would leave over budget, so the frame
    is answered `overdue` instead; the filter has taken it."""
    clock = FakeClock()
    d = _overdue_daemon("drop", budget_ms=50.0, clock=clock)
    model = d.models["pt"].model
    step = model.step_batch

    def slow(states, frames, observed, level=None):
        clock.advance(0.15)  # (the daemon's clock: three budgets pass during the step)
        return step(states, frames, observed)

    _send_frame(d, 0, clock())
    model.step_batch = slow
    try:
        d._serve()
    finally:
        del model.step_batch
    d._answer_superseded()
    assert [(type(m).__name__, m.seq, getattr(m, "reason", None)) for _, m in d.sent] == [("Drop", 0, "overdue")]
    s = d.sessions.sessions["a"]
    assert d.metrics.counters["overdue_after_step"] == 1 and s.counts["dropped_overdue"] == 1
    assert s.counts["frames_out"] == 0 and s.last_seq == 0 and s.pending is None


def test_realtime_request_without_zeromq_threads_changes_nothing_and_says_why(monkeypatch):
    """(In this test process, which has no ZeroMQ I/O thread: the request must find every I/O
    thread it was told of before it touches any thread.)"""
    from daemon import realtime

    monkeypatch.setattr(realtime, "IO_WAIT_S", 0.05)
    before = os.sched_getscheduler(0), os.sched_getparam(0).sched_priority
    rt = realtime.Realtime()
    assert rt.request(3, n_io=2) is False
    assert not rt.held and "found 0 of ZeroMQ's 2 I/O thread(s)" in rt.error
    assert (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority) == before
    assert rt.info() == {"requested_priority": 3, "held": False, "threads": {}, "error": rt.error}
    assert rt.request(None) is False and rt.error is None


def test_frames_read_together_are_dropped_in_turn_not_always_the_same_streams():
    """A bundle's frames share one receipt time: when only some can be answered in time, the
    streams dropped `overdue` most recently go first, so the drops rotate."""
    sched = Scheduler(budget_ms=4.0, max_gap=5, max_batch=64)
    sched.send_cost = 1e-3  # four sends fit in the 4 ms
    now = 100.0
    arrived = [now] * 8
    first = sched.overdue(arrived, now, [0] * 8)
    assert first == [False] * 4 + [True] * 4
    late = [0 if x is False else 1 for x in first]
    assert sched.overdue(arrived, now, late) == [True] * 4 + [False] * 4


def test_the_reload_thread_puts_itself_back_on_the_ordinary_policy():
    """Threads inherit their creator's policy: a thread started by a SCHED_RR thread (the
    serving thread starting a reload) runs SCHED_RR until realtime.ordinary() resets it."""
    import resource
    import threading

    from daemon import realtime

    if os.geteuid() != 0 and resource.getrlimit(resource.RLIMIT_RTPRIO)[0] < 1:
        pytest.skip("needs CAP_SYS_NICE or RLIMIT_RTPRIO to make a SCHED_RR thread")
    seen: dict[str, int] = {}

    def child() -> None:
        seen["inherited"] = os.sched_getscheduler(0)
        realtime.ordinary()
        seen["after"] = os.sched_getscheduler(0)

    def parent() -> None:
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(1))
        t = threading.Thread(target=child)
        t.start()
        t.join()

    t = threading.Thread(target=parent)
    t.start()
    t.join()
    assert seen == {"inherited": os.SCHED_RR, "after": os.SCHED_OTHER}


def test_a_step_within_budget_on_the_same_fake_clock_is_answered_with_its_fill():
    """(the counterpart of the overrun above: the same step taking a fifth of the budget)"""
    clock = FakeClock()
    d = _overdue_daemon("drop", budget_ms=50.0, clock=clock)
    model = d.models["pt"].model
    step = model.step_batch

    def quick(states, frames, observed, level=None):
        clock.advance(0.01)
        return step(states, frames, observed)

    model.step_batch = quick
    try:
        d.turn(clock(), items=[(wire.encode(wire.Frame("a", 0, 0.0, np.zeros(3, np.float32))), ("router", [b"p"]), clock())])
    finally:
        del model.step_batch
    assert [(type(m).__name__, m.seq) for _, m in d.sent] == [("FillMsg", 0)]
    assert d.metrics.counters.get("overdue_after_step", 0) == 0 and d.sessions.sessions["a"].counts["frames_out"] == 1


def test_idle_stream_expires_when_the_daemons_clock_passes_its_timeout():
    """Idle expiry reads the daemon's clock: advanced past idle_timeout_s, the next turn's
    housekeeping ends the silent stream and keeps the active one; nobody sleeps."""
    clock = FakeClock()
    d = _Recording.make(3, clock=clock, idle_timeout_s=2.0)
    hello = [(wire.encode(wire.Hello(sid, ["ch0", "ch1", "ch2"])), ("router", [sid.encode()]), clock())
             for sid in ("quiet", "busy")]
    d.turn(clock(), items=hello)
    assert set(d.sessions.sessions) == {"quiet", "busy"}
    for k in range(3):  # 3 x 0.9 s: "busy" sends a frame each time, "quiet" nothing
        clock.advance(0.9)
        d.turn(clock(), items=[(wire.encode(wire.Frame("busy", k, 0.0, np.zeros(3, np.float32))), ("router", [b"busy"]),
                                clock())])
        if k < 1:
            assert "quiet" in d.sessions.sessions  # 0.9 s idle: under the 2 s timeout
    assert set(d.sessions.sessions) == {"busy"}  # 2.7 s idle: expired at the turn that saw it
    assert d.metrics.counters["expired"] == 1 and d.sessions.expired == 1


@pytest.mark.realdata
def test_crbm_step_at_a_level_is_the_set_iterations_step_and_leaves_the_model_as_it_was(data):
    """The degradation level is an argument of the step: CRBMModel.step_batch(..., level=5) gives
    the fills a model set to K = 5 gives, reports K = 5, and the model still says K = 30."""
    from crbm.train import train_model
    from mocap.protocols import get_protocol

    ts = get_protocol("taylor2007").training_set()
    m = train_model(ts.sequences, ts.channels, hidden=12, epochs=3, seed=3)
    assert m.n_gibbs == 30 and m.quality_levels() == [30, 15, 7, 3, 1] and levels_of(m) == [30, 15, 7, 3, 1]
    frames = ts.sequences[0][:6].astype(np.float64)
    obs = np.ones(frames.shape, bool)
    obs[:, ::3] = False
    frames = np.where(obs, frames, np.nan)

    def run(level=None, k=None):
        m.reseed(7)
        if k is not None:
            m.set_iterations(k)
        try:
            st = [m.stream(), m.stream()]
            return [m.step_batch(st, np.stack([f, f]), np.stack([o, o]), **({} if level is None else {"level": level}))
                    for f, o in zip(frames, obs)]
        finally:
            m.set_iterations(30)

    at_level, set_to = run(level=5), run(k=5)
    assert m.n_gibbs == 30
    for a, b in zip(at_level, set_to):
        for fa, fb in zip(a, b):
            np.testing.assert_array_equal(fa.frame, fb.frame)
            assert fa.extras["gibbs_iterations"] == 5
    full = run()
    assert all(f.extras["gibbs_iterations"] == 30 for fs in full for f in fs)
    assert not all(np.array_equal(a[0].frame, b[0].frame) for a, b in zip(full, at_level))  # K matters
    with pytest.raises(ValueError):
        m.step_batch([m.stream()], frames[:1], obs[:1], level=0)
