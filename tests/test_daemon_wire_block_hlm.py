"""The bundle path's array step (``Model.step_block``: the HLM's fills, style posteriors and
phases written straight into (n, C) arrays by its one compiled call, daemon/stepblock.py)
against the row path (``step_batch``'s Fills, a message each), on real CMU frames.

Two in-process daemons, one with the array path and one without, each with its own copy of a
small HLM trained on TRAIN takes 35_01/06/07 (so each has its own state pool), get the same
fuzzed turns of bundles of 35_08's frames (the left arm lost in bursts, streams at different
offsets of the take; bundles reordered, cut short, with gaps, duplicates and late frames, single
frames beside them, re-handshakes, masks, frames overdue before and after the step): the reply
bytes must be the same, in the same order, and so must every session's state and its rows of
the model's state pool.  The same for blend's ``default`` (trained small on 35_01/06), whose own
``step_block`` (blend/withhlm.py) must have stepped the served bundles; tests/test_daemon_wire_block.py
fuzzes those with a generic styled model, and the pass-through."""
from __future__ import annotations

import msgpack
import numpy as np
import pytest

from daemon import config, wire
from daemon.models import Loaded, load_all
from tests.test_daemon_wire_block import PEER, PULL, FakeClock, Recording, _state

pytestmark = pytest.mark.realdata
ARM = ("lhumerus", "lradius", "lwrist", "lhand")


@pytest.fixture(scope="module")
def hlm(data):
    from hlm.methods import train_model
    from mocap.datasets import load_trial

    train = [load_trial(t) for t in ("35_01", "35_06", "35_07")]
    model = train_model([m.frames for m in train], train[0].channels, n_iter=3, restarts=1, styles=2)
    take = load_trial("35_08")
    return model, take.frames.astype(np.float32), list(take.channels)


def _default():
    """blend's ``default`` (an HLM expert mixed with its blend), trained small on TRAIN takes: a
    model with no array step of its own, on ``Model.step_block``'s stacked Fills."""
    from blend.withhlm import train_model
    from mocap import protocols

    ts = protocols.named_training_set(["35_01", "35_06"])
    return train_model(ts, restarts=1, n_iter=3, screen_iters=None, cycle_frames=140)


def _daemon(clock, arrays: bool, overdue: str, model):
    from daemon import server

    cfg = config.from_dict({"daemon": {"budget_ms": 4.0, "max_streams": 64, "log_level": "error", "overdue": overdue,
                                       "max_batch": 64},
                            "models": {"pt": {"builtin": "passthrough"}}, "zmq": {"router": "tcp://127.0.0.1:*"}})
    d = Recording(cfg, server.Log("error"), clock=clock)
    d.sent = []
    table, errors = load_all(cfg)
    assert not errors
    table["hlm"] = Loaded("hlm", model, table["pt"].spec, None, "now")
    d._install(table)
    d.sessions.block_path = arrays
    return d


def _pool_rows(d):
    """Each session's rows of its model's state pool (the HLM's filter and representation state)."""
    out = {}
    for sid, s in sorted(d.sessions.sessions.items()):
        if not hasattr(s.state, "slot"):
            continue
        pool, slot = s.model.pool, s.state.slot
        out[sid] = [(k, v[slot].tobytes()) for k, v in sorted({**pool.core, **pool.repr}.items())]
    return out


def _frame_map(rng, frames, arm, sid, k, seq, t, masked):
    a = frames[k % len(frames)].copy()
    obs = np.ones(a.shape, bool)
    if (k // 40) % 2:  # the arm lost 40 frames in 80
        obs[arm] = False
    if rng.random() < 0.05:  # now and then a frame with nothing but the root and a few channels
        obs[rng.random(a.shape) < 0.7] = False
    d = {"stream": sid, "seq": seq, "t": t}
    if masked:
        a[~obs] = rng.choice([np.nan, 5.0])
        d.update(angles=a.tobytes(), observed=obs.astype(np.uint8).tobytes())
    else:
        a[~obs] = np.nan
        d.update(angles=a.tobytes())
    return d


def _turns(rng, sids, channels, frames, n_turns, clock, peer):
    arm = np.array([c.split(".")[0] in ARM for c in channels])
    seqs = dict.fromkeys(sids, 0)
    offs = {sid: 37 * i for i, sid in enumerate(sids)}
    for k in range(n_turns):
        items = []
        now = clock.t + 1 / 120
        masked = bool(rng.random() < 0.3)
        t = now - 0.001 - (0.2 if rng.random() < 0.1 else 0.0)
        arrived = now - (float(rng.uniform(0.0030, 0.0040)) if rng.random() < 0.2 else 0.0)
        if k == 0 or rng.random() < 0.03:  # a (re-)handshake of one stream or all
            for sid in (sids if k == 0 else [str(rng.choice(sids))]):
                items.append((wire.encode(wire.Hello(sid, channels, "hlm")), peer, arrived))
        if rng.random() < 0.08:  # a single frame ahead of the bundle (the bundle's supersedes it)
            sid = str(rng.choice(sids))
            items.append((msgpack.packb({"v": 1, "type": "frame", **_frame_map(
                rng, frames, arm, sid, k + offs[sid], seqs[sid] + 1, t, False)}, use_bin_type=True), peer, arrived))
        for _b in range(2 if rng.random() < 0.08 else 1):
            order = list(sids)
            if rng.random() < 0.2:
                rng.shuffle(order)
            if rng.random() < 0.1:
                order = order[: int(rng.integers(1, len(order) + 1))]
            els = []
            for sid in order:
                seqs[sid] += int(rng.choice([1] * 80 + [2, 4, 0, -1]))
                els.append(_frame_map(rng, frames, arm, sid, k + offs[sid], max(seqs[sid], 0), t, masked))
            items.append((msgpack.packb({"v": 1, "type": "frames", "frames": els}, use_bin_type=True), peer, arrived))
        yield 1 / 120, items


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("case", ["drop", "serve", "drop-pull", "default-drop"])
def test_hlm_bundles_as_arrays_equal_the_row_path_bytes(hlm, case, seed, monkeypatch):
    model, frames, channels = hlm
    arrays = {"default": 0}  # default's own step_block (blend/withhlm.py) steps the served bundles
    if case.startswith("default-"):
        case = case.split("-", 1)[1]
        pair = (_default(), _default())
        assert pair[0] is not pair[1] and list(pair[0].channels) == channels
        orig = type(pair[0])._step_block
        monkeypatch.setattr(type(pair[0]), "_step_block", lambda self, *a: arrays.__setitem__(
            "default", arrays["default"] + (self is pair[0]) - (self is pair[1]) * 1000) or orig(self, *a))
    else:
        pair = (model.with_options(), model.with_options())
    rng = np.random.default_rng(100 + seed)
    clock = FakeClock()
    overdue, *via = case.split("-")
    peer = PULL if via else PEER
    fast, ref = (_daemon(clock, arrays, overdue, m) for arrays, m in zip((True, False), pair))
    n = int(rng.integers(2, 9))
    sids = [f"actor{i}" for i in range(n)]
    styled = 0
    for step, items in _turns(rng, sids, channels, frames, 50, clock, peer):
        clock.t += step
        for d in (fast, ref):
            d.sched.encode_cost, d.sched.send_cost = 20e-6, 40e-6
            d.turn(clock(), items=list(items))
        assert fast.sent == ref.sent
        assert _state(fast) == _state(ref)
        assert _pool_rows(fast) == _pool_rows(ref)
        styled += sum(b"style" in m and b"phase" in m for _, m in fast.sent)
        fast.sent.clear()
        ref.sent.clear()
    assert fast.sessions.block_served > 0 and ref.sessions.block_served == 0
    # the HLM's style posteriors and phases went out, and byte for byte alike
    assert styled > 0 or pair[0].method != "hlm"
    assert arrays["default"] > 0 or pair[0].method == "hlm"
    assert fast.sched.step_errors == ref.sched.step_errors == 0


def test_the_hlm_block_step_writes_arrays_not_fills(hlm, monkeypatch):
    """On the array path the HLM's bundle is stepped by ``step_block``'s one compiled call, and no
    ``Fill`` object is made for it: ``step_batch`` is never called for a served bundle."""
    model, frames, channels = hlm
    clock = FakeClock()
    mdl = model.with_options()
    d = _daemon(clock, True, "drop", mdl)
    calls = {"block": 0, "batch": 0}
    orig_b, orig_s = type(mdl).step_block, type(mdl).step_batch
    monkeypatch.setattr(type(mdl), "step_block", lambda self, *a, **k: calls.__setitem__("block", calls["block"] + 1)
                        or orig_b(self, *a, **k))
    monkeypatch.setattr(type(mdl), "step_batch", lambda self, *a, **k: calls.__setitem__("batch", calls["batch"] + 1)
                        or orig_s(self, *a, **k))
    sids = [f"actor{i}" for i in range(4)]
    clock.t += 1 / 120
    d.turn(clock(), items=[(wire.encode(wire.Hello(sid, channels, "hlm")), PEER, clock.t) for sid in sids])
    calls.update(block=0, batch=0)  # (a hello may warm its stream up through step_batch)
    for k in range(5):
        clock.t += 1 / 120
        els = [{"stream": sid, "seq": k, "t": clock.t, "angles": frames[k + 37 * i].tobytes()} for i, sid in enumerate(sids)]
        d.turn(clock(), items=[(msgpack.packb({"v": 1, "type": "frames", "frames": els}, use_bin_type=True),
                                PEER, clock.t)])
    assert d.sessions.block_served == 5
    assert calls == {"block": 5, "batch": 0}
