"""The online clamped-Gibbs filler behind the Filler seam (issue 4, deliverables 2 and 6).

A small model (40 hidden units, 40 epochs) trained on the real taylor2007 split keeps these fast;
the quality experiment is in test_crbm_taylor2007.py.
"""
from __future__ import annotations

import numpy as np
import pytest

from crbm.persist import load
from crbm.train import train_model
from lacuna.filler import FillerError
from lacuna.modelfile import ModelFileError, load_arrays, load_model, save_arrays
from mocap.protocols import get_protocol


@pytest.fixture(scope="module")
def split(data):
    p = get_protocol("taylor2007")
    return p.training_set(), p.cases()


@pytest.fixture(scope="module")
def model(split):
    ts, _ = split
    return train_model(ts.sequences, ts.channels, hidden=40, epochs=40, seed=3)


@pytest.fixture(scope="module")
def model2(split):
    ts, _ = split
    return train_model(ts.sequences, ts.channels, hidden=30, epochs=20, seed=4, levels=2, level2_epochs=20)


@pytest.fixture
def walk(split):
    case = next(c for c in split[1] if c.test == "35_29" and c.erased == "right-leg")
    return case.truth, case.observed


def run(model, frames, observed, seed=0):
    model.reseed(seed)
    st = model.stream()
    fills = [st.step(np.where(o, f, np.nan), o) for f, o in zip(frames, observed)]
    return np.array([f.frame for f in fills]), np.array([f.std for f in fills]), fills


def test_issue4_clamped_channels_returned_exactly(model, walk):
    frames, obs = walk
    out, std, fills = run(model, frames, obs)
    np.testing.assert_array_equal(out[obs], frames[obs])
    assert np.all(std[obs] == 0.0)
    assert np.all(np.isfinite(out)) and np.all(std[~obs] > 0)
    assert all(f.extras["gibbs_iterations"] == 30 for f in fills)
    np.testing.assert_array_equal(np.array([f.filled for f in fills]), ~obs)


def test_issue4_causal_future_frames_do_not_change_the_past(model, walk):
    frames, obs = walk
    other = frames.copy()
    t = 80
    other[t + 1 :] += 25.0          # a different future
    for mode in ("mean-field", "gibbs"):
        model.set_mode(mode)
        try:
            a, _, _ = run(model, frames, obs, seed=5)
            b, _, _ = run(model, other, obs, seed=5)
        finally:
            model.set_mode("gibbs")
        np.testing.assert_array_equal(a[: t + 1], b[: t + 1])
        assert not np.allclose(a[t + 1 :], b[t + 1 :])


def test_issue4_refuses_frames_of_the_wrong_width(model, walk):
    st = model.stream()
    with pytest.raises(FillerError, match="62 channels"):
        st.step(np.zeros(61))
    with pytest.raises(FillerError, match="observed mask"):
        st.step(np.zeros(62), np.ones(60, bool))
    bad = walk[0][0].copy()
    bad[3] = np.nan
    with pytest.raises(FillerError, match="finite"):
        st.step(bad, np.ones(62, bool))
    # the stream survives bad input and keeps filling
    assert np.all(np.isfinite(st.step(walk[0][0]).frame))


def test_issue4_save_load_round_trip(model, walk, tmp_path):
    path = tmp_path / "crbm.npz"
    model.save(str(path))
    back = load_model(str(path))
    assert type(back) is type(model) and back.channels == model.channels
    for k in ("W_", "A_", "B_", "c_", "b_"):
        np.testing.assert_array_equal(getattr(back.crbm, k), getattr(model.crbm, k))
    meta, _ = load_arrays(str(path))
    assert meta["method"] == "crbm" and meta["training"]["epochs"] == 40
    assert meta["hyperparameters"]["level1"]["n_hidden"] == 40
    frames, obs = walk
    a, sa, _ = run(model, frames, obs, seed=9)
    b, sb, _ = run(back, frames, obs, seed=9)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(sa, sb)


def test_model_file_with_wrong_shapes_is_refused_by_name(model, tmp_path):
    path = tmp_path / "crbm.npz"
    model.save(str(path))
    meta, arrays = load_arrays(str(path))
    arrays["A"] = arrays["A"][:-1]
    save_arrays(tmp_path / "bad.npz", meta, arrays)
    with pytest.raises(ModelFileError, match="array A has shape"):
        load(str(tmp_path / "bad.npz"))
    del arrays["A"]
    save_arrays(tmp_path / "bad2.npz", meta, arrays)
    with pytest.raises(ModelFileError, match="lacks 'A'"):
        load(str(tmp_path / "bad2.npz"))


@pytest.mark.parametrize("mode, bias_rate", [("mean-field", 0.0), ("gibbs", 0.0), ("gibbs", 0.05)])
def test_batched_step_equals_single_streams(model, split, mode, bias_rate):
    """Three streams, two masks (the general path) against one stream at a time (the shared-mask
    path).  The Gibbs noise is keyed by (seed, frame index), so sampling agrees too: a stream's
    fill does not depend on what else is in the batch (the daemon equals the offline fill)."""
    cases = split[1]
    leg = next(c for c in cases if c.test == "35_29" and c.erased == "right-leg")
    body = next(c for c in cases if c.test == "35_29" and c.erased == "upper-body")
    jog = next(c for c in cases if c.test == "35_18" and c.erased == "right-leg")
    T = 44
    streams = [(leg.truth[:T], leg.observed[:T]), (body.truth[:T], np.roll(body.observed[:T], -40, 0)),
               (jog.truth[:T], jog.observed[:T])]
    model.set_mode(mode)
    model.set_chains(2)
    model.bias_rate = bias_rate
    try:
        single = [run(model, f, o)[0] for f, o in streams]
        model.reseed(0)
        states = [model.stream() for _ in streams]
        batched = []
        for t in range(T):
            fr = np.stack([np.where(o[t], f[t], np.nan) for f, o in streams])
            ob = np.stack([o[t] for _, o in streams])
            batched.append([x.frame for x in model.step_batch(states, fr, ob)])
    finally:
        model.set_mode("gibbs")
        model.set_chains(1)
        model.bias_rate = 0.0
    batched = np.array(batched)
    for i in range(3):
        np.testing.assert_allclose(batched[:, i], single[i], rtol=0, atol=1e-9)


def test_chains_spread_and_degrade_knob(model, walk):
    frames, obs = walk
    one, s1, _ = run(model, frames, obs)
    model.set_chains(8)
    model.set_iterations(5)
    try:
        eight, s8, fills = run(model, frames, obs)
    finally:
        model.set_chains(1)
        model.set_iterations(30)
    assert fills[-1].extras == {"gibbs_iterations": 5, "chains": 8}
    assert np.all(np.isfinite(eight)) and np.all(s8[~obs] > 0)
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError):
            model.set_iterations(bad)
        with pytest.raises(ValueError):
            model.set_chains(bad)
    with pytest.raises(ValueError, match="mode"):
        model.set_mode("annealed")


def test_gibbs_fill_mean_approaches_mean_field_with_many_chains(model, walk):
    """One frame: the average of many Gibbs chains lands near the mean-field fill, far closer
    than a single chain typically does."""
    frames, obs = walk
    t = int(np.argmax(~obs.all(1)))
    def one_frame(mode, chains, seed):
        model.set_mode(mode)
        model.set_chains(chains)
        try:
            out, _, _ = run(model, frames[: t + 1], obs[: t + 1], seed)
        finally:
            model.set_mode("gibbs")
            model.set_chains(1)
        return out[t, ~obs[t]]
    mf = one_frame("mean-field", 1, 0)
    many = one_frame("gibbs", 256, 0)
    singles = [one_frame("gibbs", 1, s) for s in range(8)]
    d_many = np.abs(many - mf).mean()
    d_single = np.mean([np.abs(x - mf).mean() for x in singles])
    assert d_many < d_single


def test_predict_without_a_frame_keeps_going(model, walk):
    st = model.stream()
    for f in walk[0][:10]:
        st.step(f)
    for _ in range(20):
        fill = st.predict()
        assert np.all(np.isfinite(fill.frame)) and fill.filled.all()


def test_second_level_fills_and_round_trips(model2, walk, tmp_path):
    frames, obs = walk
    a, sa, _ = run(model2, frames, obs, seed=2)
    np.testing.assert_array_equal(a[obs], frames[obs])
    assert np.all(np.isfinite(a)) and np.all(sa[~obs] > 0)
    path = tmp_path / "two.npz"
    model2.save(str(path))
    back = load_model(str(path))
    assert back.level2 is not None and back.method == "crbm-2level"
    b, _, _ = run(back, frames, obs, seed=2)
    np.testing.assert_array_equal(a, b)


def test_bias_adaptation_carries_a_performers_offset_through_a_gap(model, walk, tmp_path):
    """bias_rate > 0: a performer whose right leg is held 6 degrees off the training population
    throughout is filled, once the leg goes missing, nearer their own pose than without it (the
    residual averages learned while the leg was observed shift the fill); bias_rate = 0 is the
    paper's filler, and the setting survives a save/load."""
    frames, obs = walk
    leg = ~obs.all(0)                               # the erased right-leg channels
    ang = np.array([c.rsplit(".", 1)[-1] in ("rx", "ry", "rz") for c in model.channels])
    shifted = frames.copy()
    shifted[:, leg & ang] += 6.0
    err = {}
    try:
        for rate in (0.0, 0.05):
            model.bias_rate = rate
            out, _, _ = run(model, shifted, obs)
            gap = ~obs[:, leg].any(1)
            err[rate] = float(np.sqrt(np.mean((out[gap][:, leg & ang] - shifted[gap][:, leg & ang]) ** 2)))
        assert err[0.05] < 0.8 * err[0.0], err
        model.save(str(tmp_path / "b.npz"))
        assert load_model(str(tmp_path / "b.npz")).bias_rate == 0.05
    finally:
        model.bias_rate = 0.0
    from crbm.filler import CRBMModel

    with pytest.raises(ValueError, match="bias_rate"):
        CRBMModel(model.representation, model.crbm, bias_rate=1.5)
