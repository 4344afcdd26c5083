"""``default``'s per-channel std calibration (blend/calib.py, applied in blend/withhlm.py).

Only std changes (fills bit-equal, std exactly times F[c, bin(k)]), on both mixing paths; model
files keep it and older files load with factors 1; the fit shrinks a channel with few values toward
its group; the shipped factors (blend/withhlm.json "calib") are what ``train_model`` applies.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from blend import calib
from blend.withhlm import GROUP_NAMES, SHIPPED, T_EDGES, WithHLMModel, group_index, t_bin, train_model
from lacuna import jit, modelfile
from mocap import protocols, splits

TRAIN_TAKES = ["07_02", "35_01", "walking_13", "basketball_1"]
SMALL_HLM = {"restarts": 1, "n_iter": 4, "screen_iters": None, "cycle_frames": 140}
TB = len(T_EDGES) + 1


@pytest.fixture(scope="module")
def model(data):
    ts = protocols.named_training_set(TRAIN_TAKES)
    return train_model(ts, **SMALL_HLM)


def _factors(C: int) -> np.ndarray:
    return np.exp(np.random.default_rng(1).normal(0.0, 0.5, (C, TB)))


def _run(m: WithHLMModel, truth, obs):
    st = m.stream()
    fills, stds, ks = [], [], []
    for t in range(len(truth)):
        f = st.step(truth[t], obs[t])
        fills.append(f.frame.copy())
        stds.append(f.std.copy())
        ks.append(st.k.copy())
    return np.array(fills), np.array(stds), np.array(ks)


@pytest.mark.realdata
@pytest.mark.parametrize("compiled", [True, False])
def test_calibration_changes_the_std_only(model, compiled):
    """TEST take 35_30 with the gaps protocol's bursts (seed 0): the same experts with F = 1 and with
    random factors; fills bit-equal, std exactly std x F[c, bin(k)] on every erased value."""
    if compiled and not jit.enabled():
        pytest.skip("numba cannot run in this process: only the numpy mixing serves")
    c = [c for c in protocols.Gaps(seed=0, split="test").cases() if c.test == "35_30"][0]
    truth, obs = c.truth[:700], c.observed[:700]
    F = _factors(model.n_channels)
    m0 = WithHLMModel(model.default, model.hlm, model.W, model.S, model.meta, model.tau)
    m1 = WithHLMModel(model.default, model.hlm, model.W, model.S, model.meta, model.tau, F)
    m0.compiled = m1.compiled = compiled
    a, sa, ka = _run(m0, truth, obs)
    b, sb, kb = _run(m1, truth, obs)
    assert (~obs).sum() > 1000                                   # real gaps were filled
    np.testing.assert_array_equal(a, b)                          # bit-equal fills
    np.testing.assert_array_equal(ka, kb)
    want = sa * F[np.arange(model.n_channels)[None, :], t_bin(ka)]
    np.testing.assert_allclose(sb, want, rtol=1e-12, atol=0)
    assert (sb[obs] == 0).all() and not np.allclose(sa[~obs], sb[~obs])


@pytest.mark.realdata
def test_model_file_keeps_the_calibration_and_old_files_load_with_ones(model, tmp_path):
    F = _factors(model.n_channels)
    m1 = WithHLMModel(model.default, model.hlm, model.W, model.S, model.meta, model.tau, F)
    p = str(tmp_path / "cal.npz")
    m1.save(p)
    back = modelfile.load_model(p)
    np.testing.assert_array_equal(back.calib, F)
    # a file written before the calibration existed: no "calib" array
    meta, arrays = modelfile.load_arrays(p)
    del arrays["calib"]
    old = str(tmp_path / "old.npz")
    modelfile.save_arrays(old, meta, arrays)
    back = modelfile.load_model(old)
    np.testing.assert_array_equal(back.calib, np.ones((model.n_channels, TB)))
    truth = splits.load_take("walking_27").frames[:300]
    obs = np.ones(truth.shape, bool)
    obs[100:220, :30] = False
    m0 = WithHLMModel(model.default, model.hlm, model.W, model.S, model.meta, model.tau)
    a, sa, _ = _run(m0, truth, obs)
    b, sb, _ = _run(back, truth, obs)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(sa, sb)
    # a calibration of the wrong shape is a clear error naming the file
    arrays["calib"] = np.ones((3, TB))
    bad = str(tmp_path / "bad.npz")
    modelfile.save_arrays(bad, meta, arrays)
    with pytest.raises(modelfile.ModelFileError, match="bad.npz.*calib"):
        modelfile.load_model(bad)


def test_fit_shrinks_a_channel_with_few_values_toward_its_group():
    """Constructed z = |error| / std: channel 0 three times too narrow (many values), channel 1
    right, channel 2 with 20 values ten times too narrow; channel 3 in another group."""
    rng = np.random.default_rng(0)
    n = 20000
    z = np.abs(np.concatenate([rng.normal(0, 3, n), rng.normal(0, 1, n), rng.normal(0, 10, 20), rng.normal(0, 0.5, n)]))
    chan = np.concatenate([np.zeros(n, int), np.ones(n, int), np.full(20, 2), np.full(n, 3)])
    group = np.where(chan == 3, 1, 0)
    tb = rng.integers(0, TB, len(z))
    own = calib.fit(z, chan, group, tb, 5, TB, n0=0.0, n1=np.inf)
    assert own.shape == (5, TB) and np.allclose(own, own[:, :1])    # no time-bin part with N1 = inf
    assert abs(own[0, 0] - 3.0) < 0.15 and abs(own[1, 0] - 1.0) < 0.05 and abs(own[3, 0] - 0.5) < 0.03
    assert own[2, 0] > 5.0                                           # its own 20 values: fitted to them
    shrunk = calib.fit(z, chan, group, tb, 5, TB, n0=2000.0, n1=np.inf)
    g0 = np.exp(np.log(np.quantile(z[group == 0], calib.Q) / 2))
    assert abs(shrunk[2, 0] - g0) < 0.1 * g0                         # 20 values vs N0 2000: the group's
    assert abs(shrunk[0, 0] - own[0, 0]) < 0.1 * own[0, 0]           # 20000 values: still its own
    assert shrunk[4, 0] == 1.0                                       # a channel with no value and no group
    # a channel never off (error 0 everywhere): no evidence, its group's factor, not the floor
    still = calib.fit(np.concatenate([z, np.zeros(5000)]), np.concatenate([chan, np.full(5000, 4)]),
                      np.concatenate([group, np.zeros(5000, int)]), np.concatenate([tb, np.zeros(5000, int)]),
                      5, TB, n0=0.0, n1=np.inf)
    assert still[4, 0] > 1.0
    # a time-bin part: errors twice as wide in bin 5 for every channel of group 0
    z2 = np.where((tb == 5) & (group == 0), 2 * z, z)
    tf = calib.fit(z2, chan, group, tb, 5, TB, n0=0.0, n1=0.0)
    assert tf[1, 5] / tf[1, 0] > 1.6 and abs(tf[3, 5] / tf[3, 0] - 1) < 0.1
    # a channel x time-bin part: only channel 1 twice as wide in bin 6 (its group's other channel not)
    z3 = np.where((tb == 6) & (chan == 1), 2 * z, z)
    no = calib.fit(z3, chan, group, tb, 5, TB, n0=0.0, n1=np.inf)
    ct = calib.fit(z3, chan, group, tb, 5, TB, n0=0.0, n1=np.inf, n2=0.0)
    assert np.allclose(no, no[:, :1])
    assert ct[1, 6] / ct[1, 0] > 1.6 and abs(ct[0, 6] / ct[0, 0] - 1) < 0.1
    half = calib.fit(z3, chan, group, tb, 5, TB, n0=0.0, n1=np.inf, n2=float(((tb == 6) & (chan == 1)).sum()))
    assert 1.2 < half[1, 6] / half[1, 0] < ct[1, 6] / ct[1, 0]     # N2 = its values: half the log step


def test_json_round_trip_gives_other_skeletons_their_groups_factor():
    ch = ["root.rz", "lfemur.rx", "lfemur.ry"]
    gch = group_index(ch)
    F = np.array([[2.0] * TB, [0.5] * TB, [2.0] * TB])
    d = json.loads(json.dumps(calib.to_json(F, ch, gch, GROUP_NAMES, {"N0": 0})))
    np.testing.assert_allclose(calib.from_json(d, ch, gch, GROUP_NAMES, TB), F)
    other = ["root.rz", "lfemur.rw", "hand.rx"]          # a channel not in the file, of a known group
    og = group_index(other)
    G = calib.from_json(d, other, og, GROUP_NAMES, TB)
    assert G[0, 0] == 2.0 and abs(G[1, 0] - 1.25) < 1e-3  # lfemur's group: the median of 0.5 and 2
    np.testing.assert_allclose(calib.from_json(None, other, og, GROUP_NAMES, TB), 1.0)


@pytest.mark.realdata
def test_train_model_applies_the_shipped_factors(model):
    d = json.loads(SHIPPED.read_text())
    assert "calib" in d, "blend/withhlm.json has no calibration (bench/default_calib.py fit --write)"
    want = calib.from_json(d["calib"], model.channels, model.group, GROUP_NAMES, TB)
    np.testing.assert_array_equal(model.calib, want)
    assert set(d["calib"]["channels"]) == set(model.channels)     # fitted on this skeleton's every channel
    assert not np.allclose(want, 1.0)
