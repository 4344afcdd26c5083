"""daemon.prewarm: rehearsing the last frame before the next is due changes nothing a stream sees.

In process: a real HLM (trained in seconds on three subject-35 walks) behind the real Daemon
object, its answers recorded instead of sent; one daemon rehearses before every frame, the other
never, and their fills must be the same bytes.  Over sockets: a daemon process paced at 120 Hz
rehearses between its frames and its fills equal the model's own stream.

No wall-clock figure is asserted: how many frames found a rehearsal before them, and the period
the daemon measured, are figures of the machine's load; bench/prewarm_ab.sh reports both (the
`rehearsed` and `period` columns) beside the latency each lead buys."""
from __future__ import annotations

import time

import numpy as np
import pytest

from daemon import config, prewarm, server, wire

PERIOD = 1.0 / 120.0


@pytest.fixture(scope="module")
def hlm_walk(small_walk_hlm):
    from lacuna.modelfile import load_model
    from mocap.datasets import load_trial

    path = small_walk_hlm
    channels = list(load_model(path).channels)
    test = load_trial("35_08").frames[:120].astype(np.float32)
    miss = np.array([c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "lhand") for c in channels])
    test[:, miss] = np.nan
    return str(path), channels, test


class _Recording(server.Daemon):
    def _send(self, origin, msg, publish=False):
        self.sent.append(msg)


def _daemon(model_file: str, prewarm_ms: float) -> _Recording:
    cfg = config.from_dict({"daemon": {"budget_ms": 1000.0, "log_level": "error", "overdue": "serve",
                                       "prewarm_ms": prewarm_ms},
                            "models": {"hlm": {"file": model_file}}, "zmq": {"router": "tcp://127.0.0.1:*"}})
    d = _Recording(cfg, server.Log("error"))
    d.sent = []
    from daemon.models import load_all

    table, errors = load_all(cfg)
    assert not errors
    d._install(table)
    return d


def _modest_cost(d: _Recording, sid: str) -> None:
    """The model's step cost estimate, as a quiet machine measures it (a loaded test machine's
    warm-up may have measured one over MAX_STEP_S, and then no rehearsal is planned: tested below)."""
    cm = d.sched.cost(d.sessions.sessions[sid].model, None)
    cm.s, cm.seen = [0.0] * 5, False
    cm.observe(1, 100e-6)


def _serve(d: _Recording, sid: str, seq: int, values: np.ndarray, arrived: float) -> wire.FillMsg:
    d.sent.clear()
    d._batch([(wire.encode(wire.Frame(sid, seq, seq * PERIOD, values)), ("router", [b"p"]), arrived)])
    d._serve()
    (m,) = d.sent
    assert isinstance(m, wire.FillMsg)
    return m


def _snapshot(d: _Recording, sid: str):
    s = d.sessions.sessions[sid]
    pool = s.model.pool
    row = {k: v[s.state.slot].copy() for k, v in (*pool.core.items(), *pool.repr.items())}
    costs = {k: list(c.s) for k, c in d.sched.costs.items()}
    return row, costs, dict(s.counts), s.last_seq, s.model_seq, s.last_out.copy(), dict(d.metrics.counters)


def _same(a, b) -> bool:
    row_a, *rest_a = a
    row_b, *rest_b = b
    return (row_a.keys() == row_b.keys() and all(np.array_equal(row_a[k], row_b[k]) for k in row_a)
            and all(np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y for x, y in zip(rest_a, rest_b)))


def test_rehearsing_before_every_frame_changes_no_fill_and_no_state(hlm_walk):
    path, channels, test = hlm_walk
    warm, plain = _daemon(path, 0.5), _daemon(path, 0.0)
    for d in (warm, plain):
        d.sessions.hello(wire.Hello("walk", channels))
        _modest_cost(d, "walk")
    t0 = time.perf_counter()
    for t in range(test.shape[0]):
        arrived = t0 + t * PERIOD  # a capture clock's receipt times (the turns themselves run back to back)
        if t >= 4:
            # a frame is due: the warm daemon has planned its rehearsal, and the rehearsal leaves
            # the stream's filter row, its counters, the scheduler's costs and the metrics as they were
            due = warm.prewarm.due
            assert due is not None and arrived - PERIOD < due < arrived
            before, n_sent = _snapshot(warm, "walk"), len(warm.sent)
            warm.prewarm.rehearse(warm.sessions.sessions, warm.sched, wire.encode)
            assert warm.prewarm.due is None and len(warm.sent) == n_sent  # nothing was sent
            assert _same(before, _snapshot(warm, "walk"))
        a, b = _serve(warm, "walk", t, test[t], arrived), _serve(plain, "walk", t, test[t], arrived)
        assert a.angles.tobytes() == b.angles.tobytes() and a.std.tobytes() == b.std.tobytes()
        assert a.style.tobytes() == b.style.tobytes() and a.phase == b.phase and a.status == b.status == "ok"
        assert a.filled.any()  # the arm is filled: the fills depend on the filter's state
    assert warm.prewarm.count == test.shape[0] - 4 and warm.prewarm.errors == 0
    assert plain.prewarm.count == 0 and plain.prewarm.due is None
    info = warm.status()["prewarm"]
    assert info["rehearsals"] == warm.prewarm.count and abs(info["period_ms"] - 1000 * PERIOD) < 0.01
    # a rehearsal really steps the model (on its shadow state): the shadow has consumed frames
    ((model, shadow),) = warm.prewarm._shadows.values()
    assert int(model.pool.core["t"][shadow.slot]) == warm.prewarm.count


def test_a_rehearsal_is_planned_only_for_a_regular_stream_fast_enough_to_gain(hlm_walk):
    path, channels, test = hlm_walk
    d = _daemon(path, 0.5)
    d.sessions.hello(wire.Hello("walk", channels))
    _modest_cost(d, "walk")
    t0 = time.perf_counter()
    for t in range(3):  # two gaps: not enough to call it a period
        _serve(d, "walk", t, test[t], t0 + t * PERIOD)
        assert d.prewarm.due is None
    _serve(d, "walk", 3, test[3], t0 + 3 * PERIOD)
    s = d.sessions.sessions["walk"]
    step = d.sched.cost(s.model, None).estimate(1)
    assert d.prewarm.due == pytest.approx(t0 + 4 * PERIOD - 0.0005 - step, abs=1e-9)
    # frames of a burst (closer than MIN_GAP_S) do not count as the period
    _serve(d, "walk", 4, test[4], t0 + 3 * PERIOD + 0.0002)
    assert d.prewarm.period() == pytest.approx(PERIOD, abs=1e-9)
    # a stream slower than MAX_PERIOD_S is not rehearsed for
    slow = prewarm.Prewarm(0.5)
    for k in range(5):
        slow.served(s, wire.Frame("walk", k, 0.0, test[0]), t0 + k * 0.2, d.sched)
    assert slow.period() == pytest.approx(0.2) and slow.due is None
    # nor for one faster than MIN_PERIOD_S (its own frames keep the path warm: 4x overload of 120 Hz)
    fast_ = prewarm.Prewarm(0.5)
    for k in range(5):
        fast_.served(s, wire.Frame("walk", k, 0.0, test[0]), t0 + k * 0.002, d.sched)
    assert fast_.period() == pytest.approx(0.002) and fast_.due is None
    # nor for a model whose step is estimated over MAX_STEP_S (a rehearsal would still be running
    # when the frame lands)
    cm = d.sched.cost(s.model, None)
    for _ in range(200):
        cm.observe(1, 0.01)
    _serve(d, "walk", 5, test[5], t0 + 5 * PERIOD)
    assert d.prewarm.due is None


def test_a_stream_gone_since_is_not_rehearsed_and_a_failing_rehearsal_costs_no_frame(hlm_walk, monkeypatch):
    path, channels, test = hlm_walk
    d = _daemon(path, 0.5)
    d.sessions.hello(wire.Hello("walk", channels))
    _modest_cost(d, "walk")
    t0 = time.perf_counter()
    for t in range(5):
        _serve(d, "walk", t, test[t], t0 + t * PERIOD)
    assert d.prewarm.due is not None
    d.sessions.reset("walk")
    d.prewarm.rehearse(d.sessions.sessions, d.sched, wire.encode)
    assert d.prewarm.count == 0 and d.prewarm.errors == 0 and d.prewarm.due is None
    # a model that fails in the rehearsal: counted, the shadow dropped, and the next frame is served
    d.sessions.hello(wire.Hello("walk", channels))
    for t in range(5):
        _serve(d, "walk", t, test[t], t0 + (5 + t) * PERIOD)
    model = d.sessions.sessions["walk"].model
    real = type(model).step_batch

    def step_batch(self, states, frames, observed):
        if any(x is shadow for x in states for _, shadow in d.prewarm._shadows.values()):
            raise RuntimeError("shadow step failed")
        return real(self, states, frames, observed)

    monkeypatch.setattr(type(model), "step_batch", step_batch)
    d.prewarm.rehearse(d.sessions.sessions, d.sched, wire.encode)
    assert d.prewarm.errors == 1 and "shadow step failed" in d.prewarm.last_error and not d.prewarm._shadows
    m = _serve(d, "walk", 5, test[5], t0 + 10 * PERIOD)
    assert m.status == "ok" and m.seq == 5


def test_a_reload_drops_the_shadows_and_takes_the_new_lead(hlm_walk):
    path, channels, test = hlm_walk
    d = _daemon(path, 0.5)
    d.sessions.hello(wire.Hello("walk", channels))
    t0 = time.perf_counter()
    for t in range(5):
        _serve(d, "walk", t, test[t], t0 + t * PERIOD)
    d.prewarm.rehearse(d.sessions.sessions, d.sched, wire.encode)
    assert d.prewarm._shadows
    from daemon.models import load_all

    table, errors = load_all(d.cfg)  # a fresh load of the file, as a SIGHUP makes: new model objects
    assert not errors
    d._install(table)
    assert not d.prewarm._shadows and d.prewarm.due is None


def test_a_daemon_paced_at_120_hz_rehearses_before_its_frames_and_fills_as_the_model_does(hlm_walk, tmp_path):
    """The daemon as a process, a DEALER sending the walk at 120 Hz on loopback: it rehearses
    between frames (status says how often, and the period it found), its fills are the model's
    own causal stream's; with prewarm_ms = 0 it never rehearses.  After a rehearsal it spins for the
    frame it warmed for (prewarm_spin_ms, bench/notebook/spin-38.md), and with a spin window longer
    than the frame period a spin is ended by the frame it waited for.  What it checks: every frame
    is answered, in order, with the model's fill; the default lead rehearses without error, reports
    a period and spins after its rehearsals; a 20 ms window catches frames; spin 0 never spins; lead
    0 never rehearses nor spins."""
    import zmq

    from clients.control import control
    from clients.harness import DaemonProcess
    from lacuna.modelfile import load_model

    path, channels, test = hlm_walk
    ctx = zmq.Context()
    procs = []
    try:
        for lead, spin in ((None, None), (None, 20.0), (None, 0.0), (0.0, None)):
            cfg = tmp_path / f"lacuna-{lead}-{spin}.toml"
            cfg.write_text("[daemon]\nbudget_ms = 250.0\nlog_level = \"warning\"\n"
                           + ("" if lead is None else f"prewarm_ms = {lead}\n")
                           + ("" if spin is None else f"prewarm_spin_ms = {spin}\n")
                           + f"[models.hlm]\nfile = \"{path}\"\n[zmq]\nrouter = \"tcp://127.0.0.1:*\"\n")
            d = DaemonProcess(str(cfg))
            procs.append(d)
            d.start()
            s = ctx.socket(zmq.DEALER)
            s.setsockopt(zmq.LINGER, 0)
            s.connect(d.endpoints["router"])
            s.send(wire.encode(wire.Hello("walk", channels)))
            assert s.poll(30000) and isinstance(wire.decode(s.recv()), wire.HelloAck)
            ref = load_model(path).stream()
            t0 = time.perf_counter() + 0.05
            for t in range(test.shape[0]):
                while time.perf_counter() < t0 + t * PERIOD:  # pacing IS the behaviour: a 120 Hz stream
                    time.sleep(0.0002)
                s.send(wire.encode(wire.Frame("walk", t, t * PERIOD, test[t])))
                assert s.poll(30000), "no answer from the daemon"
                m = wire.decode(s.recv())
                assert isinstance(m, wire.FillMsg) and m.status == "ok", m
                r = ref.step(test[t].astype(np.float64), ~np.isnan(test[t]))
                assert m.angles.tobytes() == np.where(np.isnan(test[t]), r.frame.astype(np.float32), test[t]).tobytes()
                assert m.std.tobytes() == r.std.astype(np.float32).tobytes()
            s.close(0)
            info = control(d.endpoints["router"], "status", timeout_s=5.0).result["prewarm"]
            if lead is None:  # the default: on
                assert info["lead_ms"] == config.PREWARM_MS and info["errors"] == 0
                # (how many: a frame that came early, or a stall of the machine, costs a rehearsal;
                # the share, and the period found, are measured by bench/prewarm_ab.sh)
                assert 1 <= info["rehearsals"] <= test.shape[0], info
                assert info["period_ms"] is not None and info["period_ms"] > 0, info
                # a spin follows a rehearsal unless the frame had already landed
                assert info["spin_caught"] <= info["spins"] <= info["rehearsals"], info
                if spin == 0.0:
                    assert info["spins"] == 0 and info["spin_ms"] == 0.0, info
                elif spin == 20.0:  # (longer than the 8.3 ms period: the next frame ends it)
                    assert info["spin_caught"] >= 1 and info["spin_ms"] > 0.0, info
            else:
                assert info["lead_ms"] == 0.0 and info["rehearsals"] == 0 and info["spins"] == 0, info
    finally:
        for d in procs:
            if d.proc is not None and d.proc.poll() is None:
                d.proc.kill()
                d.proc.wait(10)
        ctx.term()


def test_a_frame_that_lands_during_a_rehearsal_counts_the_rehearsal_in_its_proc_us(tmp_path):
    """The daemon's own loop (Daemon.run on a thread, real ROUTER socket, a DEALER pacing a
    pass-through stream at 120 Hz) with one rehearsal made slow: it waits, inside the rehearsal,
    until the next frame has landed on the daemon's socket and then holds on a while.  That frame
    waited for the rest of the rehearsal, so its ``proc_us`` and the latency ``status`` reports
    must cover that wait (stamped when read, after the rehearsal, both would show only the
    fill's own microseconds)."""
    import threading

    import zmq

    from clients.control import control

    hold_s = 0.05  # how long the slow rehearsal goes on after the frame landed
    cfg = config.from_dict({"daemon": {"budget_ms": 1000.0, "log_level": "error", "overdue": "serve"},
                            "models": {"pt": {"builtin": "passthrough"}}, "zmq": {"router": "tcp://127.0.0.1:*"}})
    d = server.Daemon(cfg, server.Log("error"))
    d.start()
    real = d.prewarm.rehearse
    held: dict[str, float] = {}

    def slow_rehearse(*args):
        # (on the daemon's thread: poll() looks at its sockets without reading them)
        if not held:
            assert d.net is not None and d.net.poll(10_000), "no frame landed during the rehearsal"
            held["landed"] = time.perf_counter()
            real(*args)
            while time.perf_counter() < held["landed"] + hold_s:
                time.sleep(0.001)
            held["ended"] = time.perf_counter()
        else:
            real(*args)

    d.prewarm.rehearse = slow_rehearse
    loop = threading.Thread(target=d.run, name="daemon-loop")
    loop.start()
    ctx = zmq.Context()
    s = ctx.socket(zmq.DEALER)
    s.setsockopt(zmq.LINGER, 0)
    try:
        endpoint = d.endpoints()["router"]
        s.connect(endpoint)
        s.send(wire.encode(wire.Hello("a", ["c0", "c1", "c2"])))
        assert s.poll(30000) and isinstance(wire.decode(s.recv()), wire.HelloAck)
        t0 = time.perf_counter() + 0.01
        got = None
        for t in range(240):  # until a rehearsal has held a frame (a regular period is needed first)
            while time.perf_counter() < t0 + t * PERIOD:  # pacing IS the behaviour: a 120 Hz stream
                time.sleep(0.0002)
            was_held = "landed" in held
            s.send(wire.encode(wire.Frame("a", t, t * PERIOD, np.zeros(3, np.float32))))
            assert s.poll(30000), "no answer from the daemon"
            m = wire.decode(s.recv())
            assert isinstance(m, wire.FillMsg) and m.seq == t, m
            if not was_held and "ended" in held:  # the frame the slow rehearsal held
                got = m
                break
        assert got is not None, "no rehearsal ran in 240 frames"
        waited_us = int((held["ended"] - held["landed"]) * 1e6)
        assert got.proc_us >= waited_us, (got.proc_us, waited_us)
        lat = control(endpoint, "status", timeout_s=5.0).result["latency"]
        assert lat["max_ms"] >= waited_us / 1e3, (lat, waited_us)
    finally:
        s.close(0)
        d.flag_stop = True
        loop.join(30)
        ctx.term()
    assert not loop.is_alive()


def test_the_spin_after_a_rehearsal_follows_the_config_and_never_runs_real_time():
    """prewarm_spin_ms is read at each wait (a reload changes it), and a daemon asked for SCHED_RR
    never spins after a rehearsal: a spinning real-time thread keeps the kernel's own network work
    off its core (why busy_poll_ms is refused with realtime_priority)."""
    def waiting(**daemon):
        cfg = config.from_dict({"daemon": {"log_level": "error", **daemon},
                                "models": {"m": {"builtin": "passthrough"}}, "zmq": {"router": "tcp://127.0.0.1:*"}})
        return server.Daemon(cfg, server.Log("error"))

    assert waiting()._pre_spin_s == config.PREWARM_SPIN_MS / 1000.0 > 0.0
    d = waiting(prewarm_spin_ms=0.5)
    assert d._pre_spin_s == 0.0005
    d.cfg.prewarm_spin_ms = 3.0   # (read at every wait, so the cfg a reload installs counts at once)
    assert d._pre_spin_s == 0.003
    assert waiting(prewarm_spin_ms=0.0)._pre_spin_s == 0.0
    assert waiting(realtime_priority=5)._pre_spin_s == 0.0
    assert waiting(realtime_priority=5, prewarm_spin_ms=2.0)._pre_spin_s == 0.0
