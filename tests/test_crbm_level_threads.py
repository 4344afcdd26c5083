"""Models are immutable (shared/DESIGN.md): the CRBM's degradation level is an argument of the
step, handed down to its kernels, never a setting flipped on the model for the call.

Small CRBMs trained on the real taylor2007 split (a single model, a two-level model and a
two-member ensemble); real 35_29 frames with the right leg erased.
"""
from __future__ import annotations

import threading

import numpy as np
import pytest

from crbm.generate import generate
from crbm.train import train_model
from mocap.protocols import get_protocol

N_FRAMES = 24
N_STREAMS = 3


@pytest.fixture(scope="module")
def split(data):
    p = get_protocol("taylor2007")
    return p.training_set(), p.cases()


@pytest.fixture(scope="module", params=["crbm", "crbm-2level", "crbm-ens"])
def model(request, split):
    ts, _ = split
    kw = {"crbm": {}, "crbm-2level": {"levels": 2, "level2_epochs": 3},
          "crbm-ens": {"members": 2, "method": "crbm-ens"}}[request.param]
    return train_model(ts.sequences, ts.channels, hidden=16, epochs=4, seed=3, **kw)


@pytest.fixture(scope="module")
def walk(split):
    case = next(c for c in split[1] if c.test == "35_29" and c.erased == "right-leg")
    start = int(np.flatnonzero(~case.observed.all(1))[0]) - 6  # six observed frames, then the gap
    obs = case.observed[start:start + N_FRAMES]
    assert (~obs).any()
    return np.where(obs, case.truth[start:start + N_FRAMES], np.nan), obs


def knobs_of(model) -> dict:
    """Everything a step could change: the model's attributes (its state pool and mask cache aside,
    which hold streams and derived arrays) and, for an ensemble, every member's."""
    def of(m):
        out = {}
        for k, v in vars(m).items():
            if k in ("_pool", "_mask_cache", "_members"):
                continue
            out[k] = v.bit_generator.state if isinstance(v, np.random.Generator) else v
        return out
    snap = {"self": of(model)}
    for i, mm in enumerate(getattr(model, "_members", [])):
        snap[f"member{i}"] = of(mm)
    return snap


def assert_same_knobs(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for who in a:
        assert a[who].keys() == b[who].keys(), who
        for k in a[who]:
            x, y = a[who][k], b[who][k]
            if isinstance(x, np.ndarray):
                assert np.array_equal(x, y), (who, k)
            else:
                assert x == y, (who, k, x, y)


def step_all(model, streams, frames, obs, level, sync=None) -> list[list]:
    out = []
    for f, o in zip(frames, obs):
        if sync is not None:
            sync.wait()
        fills = model.step_batch(streams, np.stack([f] * len(streams)), np.stack([o] * len(streams)), level=level)
        out.append([(x.frame.copy(), x.std.copy(), dict(x.extras)) for x in fills])
    return out


def assert_equal_fills(a, b) -> None:
    assert len(a) == len(b)
    for ta, tb in zip(a, b):
        for (fa, sa, ea), (fb, sb, eb) in zip(ta, tb):
            np.testing.assert_array_equal(fa, fb)
            np.testing.assert_array_equal(sa, sb)
            assert ea == eb


@pytest.mark.realdata
def test_concurrent_steps_at_two_levels_equal_the_same_steps_one_after_the_other(model, walk):
    frames, obs = walk
    low = model.quality_levels()[-2]  # a cheaper level than the model's own K
    assert low < model.n_gibbs
    # one after the other: full quality on three streams, then the cheaper level on three others
    ref_full = step_all(model, [model.stream() for _ in range(N_STREAMS)], frames, obs, None)
    ref_low = step_all(model, [model.stream() for _ in range(N_STREAMS)], frames, obs, low)
    assert all(e["gibbs_iterations"] == model.n_gibbs for t in ref_full for _, _, e in t)
    assert all(e["gibbs_iterations"] == low for t in ref_low for _, _, e in t)
    assert not np.array_equal(ref_full[-1][0][0], ref_low[-1][0][0])  # the levels give different fills
    # at once: two threads on the same model, every frame started together (a barrier per frame)
    full_streams = [model.stream() for _ in range(N_STREAMS)]
    low_streams = [model.stream() for _ in range(N_STREAMS)]  # (all streams exist before either thread runs)
    sync = threading.Barrier(2, timeout=60)
    got: dict[str, list] = {}
    errors: list[BaseException] = []

    def worker(name, streams, level):
        try:
            got[name] = step_all(model, streams, frames, obs, level, sync)
        except BaseException as e:  # noqa: BLE001 - reported below
            errors.append(e)
            sync.abort()

    threads = [threading.Thread(target=worker, args=("full", full_streams, None)),
               threading.Thread(target=worker, args=("low", low_streams, low))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert not errors, errors
    assert_equal_fills(got["full"], ref_full)
    assert_equal_fills(got["low"], ref_low)


@pytest.mark.realdata
def test_a_step_at_any_level_leaves_the_model_as_it_was(model, walk):
    frames, obs = walk
    before = knobs_of(model)
    streams = [model.stream() for _ in range(2)]
    for level in [*model.quality_levels(), None, 4, model.n_gibbs]:
        for f, o in zip(frames[:3], obs[:3]):
            fills = model.step_batch(streams, np.stack([f, f]), np.stack([o, o]), level=level)
            assert fills[0].extras["gibbs_iterations"] == (model.n_gibbs if level is None else level)
        assert_same_knobs(knobs_of(model), before)
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="Gibbs iterations"):
            model.step_batch(streams, frames[:2], obs[:2], level=bad)
    assert_same_knobs(knobs_of(model), before)


@pytest.mark.realdata
def test_generation_steps_a_variant_and_leaves_the_model_as_it_was(model, split):
    ts, _ = split
    seed_frames = ts.sequences[0][:8].astype(np.float64)
    before = knobs_of(model)
    a = generate(model, seed_frames, 6, seed=11, n_gibbs=3)
    assert_same_knobs(knobs_of(model), before)
    b = generate(model, seed_frames, 6, seed=11, n_gibbs=3)
    np.testing.assert_array_equal(a, b)  # the same seed, the same motion
    assert not np.array_equal(a, generate(model, seed_frames, 6, seed=12, n_gibbs=3))
    # a variant is a model of its own: its knobs, its streams; the original keeps its own
    v = model.variant(n_chains=1, mode="gibbs", seed=11, n_gibbs=3)
    assert (v.n_gibbs, v.n_chains, v._seed) == (3, 1, 11) and v.pool is not model.pool
    assert_same_knobs(knobs_of(model), before)
