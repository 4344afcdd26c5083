"""The representation's inverse reproduces the original frames; the stream equals the batch."""
import numpy as np
import pytest

from mocap.datasets import load_trial
from mocap.representation import Representation, resample, wrap180


@pytest.fixture(scope="module")
def walks(data):
    return [load_trial(t) for t in ("07_02", "35_01", "35_17")]


@pytest.mark.parametrize("root_mode", ["relative", "raw"])
@pytest.mark.parametrize("normalize", [True, False])
def test_inverse_reproduces_original_frames(data, walks, root_mode, normalize):
    rep = Representation.fit([m.frames for m in walks], walks[0].channels, root_mode, normalize)
    for trial in ("07_01", "35_29", "02_01"):
        m = load_trial(trial)
        feats = rep.transform(m.frames)
        back = rep.inverse(feats, first=m.frames[0])
        err = np.abs(wrap180(back - m.frames))
        kept = np.asarray(rep.keep)
        assert err[:, kept].max() < 1e-8, (trial, m.channels[int(err.max(0).argmax())], err.max())
        # dropped (constant) channels come back as the training constant, equal to the rebuilt
        # files' rounding (~1e-4 degrees)
        assert err[:, ~kept].max() < 1e-3


def test_constant_channels_dropped_and_restored(data, walks):
    rep = Representation.fit([m.frames for m in walks], walks[0].channels)
    dropped = [c for c, k in zip(rep.channels, rep.keep) if not k]
    assert sorted(dropped) == sorted(["lclavicle.ry", "lclavicle.rz", "lfingers.rx", "rclavicle.ry", "rclavicle.rz", "rfingers.rx"])
    assert rep.n_features == 62 - 6  # 6 root channels become 6 root features
    assert not set(dropped) & set(rep.features)


def test_normalised_features_have_unit_variance_on_training(data, walks):
    rep = Representation.fit([m.frames for m in walks], walks[0].channels)
    f = np.vstack([rep.transform(m.frames) for m in walks])
    np.testing.assert_allclose(f.mean(0), 0, atol=1e-9)
    np.testing.assert_allclose(f.std(0), 1, atol=1e-9)


def test_stream_encode_equals_transform_and_decode_passes_observed_exactly(data, walks):
    rep = Representation.fit([m.frames for m in walks], walks[0].channels)
    m = load_trial("07_01")
    feats = rep.transform(m.frames)
    st = rep.new_state(1)
    rng = np.random.default_rng(0)
    for t in range(m.n_frames):
        # frame 0 fully observed: absolute root position cannot come from displacements
        obs = rng.random(62) > 0.3 if t else np.ones(62, bool)
        x = np.where(obs, m.frames[t], np.nan)[None]
        f, fo = st.encode(x, obs[None])
        # every feature marked observed equals the batch transform; the rest are NaN
        np.testing.assert_allclose(f[fo], feats[t][fo[0]], atol=1e-9)
        assert np.isnan(f[~fo]).all()
        out = st.decode(np.where(fo, f, feats[t][None]), x, obs[None])
        assert np.array_equal(out[0][obs], m.frames[t][obs])  # observed: bit-exact pass-through
        st.commit(out)
        kept = np.asarray(rep.keep)
        assert np.abs(wrap180(out[0] - m.frames[t]))[kept].max() < 1e-8


def test_root_features_invariant_to_ground_plane_rotation_and_translation(data, walks):
    """Taylor et al.: the representation is invariant to ground-plane translation and to rotation
    about the vertical.  Rotate and shift a whole take about Y; the features must not change."""
    from mocap.representation import _matrix_to_rxyz, _rxyz_to_matrix

    rep = Representation.fit([m.frames for m in walks], walks[0].channels)
    m = load_trial("35_29")
    f0 = rep.transform(m.frames)
    th = np.deg2rad(73.0)
    Ry = np.array([[np.cos(th), 0, np.sin(th)], [0, 1, 0], [-np.sin(th), 0, np.cos(th)]])
    moved = m.frames.copy()
    pos = m.index(["root.tx", "root.ty", "root.tz"])
    rot = m.index(["root.rx", "root.ry", "root.rz"])
    moved[:, pos] = m.frames[:, pos] @ Ry.T + np.array([100.0, 0.0, -40.0])
    r = np.deg2rad(m.frames[:, rot])
    R = Ry[None] @ _rxyz_to_matrix(r[:, 0], r[:, 1], r[:, 2])
    moved[:, rot] = _matrix_to_rxyz(R, m.frames[:, rot])
    f1 = rep.transform(moved)
    np.testing.assert_allclose(f1, f0, atol=1e-7)


def test_unwrap_is_continuous_across_the_180_boundary():
    ch = ["root.tx", "root.ty", "root.tz", "root.rx", "root.ry", "root.rz", "a.rx"]
    t = np.arange(200)
    frames = np.zeros((200, 7))
    frames[:, 1] = 15
    frames[:, 6] = wrap180(150 + t * 0.5)  # crosses +180 at t=60
    rep = Representation.fit([frames], ch, normalize=False)
    f = rep.transform(frames)
    j = rep.features.index("a.rx")
    np.testing.assert_allclose(np.diff(f[:, j]), 0.5)  # no 360-degree jump where the raw value wraps
    assert np.ptp(f[:, j]) == pytest.approx(99.5)
    back = rep.inverse(f, first=frames[0])
    assert np.abs(wrap180(back - frames)).max() < 1e-9


def test_resample_120_to_30_keeps_every_fourth_frame(data):
    m = load_trial("35_29")
    r = resample(m.frames, 120, 30)
    assert r.shape[0] == 125
    np.testing.assert_array_equal(r, m.frames[::4])
    r2 = resample(m.frames, 120, 50, m.channels)
    assert abs(r2.shape[0] - round(m.n_frames * 50 / 120)) <= 1
    np.testing.assert_allclose(r2[0], m.frames[0])


def test_representation_json_round_trip_and_validation(data, walks):
    import json

    rep = Representation.fit([m.frames for m in walks], walks[0].channels)
    d = json.loads(json.dumps(rep.to_dict()))
    rep2 = Representation.from_dict(d)
    m = load_trial("07_01")
    np.testing.assert_array_equal(rep2.transform(m.frames), rep.transform(m.frames))
    d["std"] = d["std"][:-1]
    with pytest.raises(ValueError, match="std"):
        Representation.from_dict(d)


def test_root_std_rule_grows_with_the_gap_and_round_trips(data, walks):
    """The fitted rule for a missing root's ground-position std (``root_std`` [a, p, c, w, u]): over
    a real walk's root dropout, undamped (every increment kept, so Q = w x the filled speed + u x the
    model's std, summed), the std after g frames is a g^(p-1) (Q + c g), computed here from the fill
    and its std; [1, 1, 0, 0, 1] is the summed std exactly; observed frames carry none; the rule
    survives the model file's dict, a dict written before it loads with the summed std, and a
    malformed rule is refused."""
    import json

    rule = [0.39, 0.97, 0.07, 0.45, 0.3]
    rep = Representation.fit([m.frames for m in walks], walks[0].channels, normalize=False, root_std=rule)
    truth = load_trial("35_08").frames[:260]
    obs = np.ones(truth.shape, bool)
    root = [i for i, c in enumerate(rep.channels) if c.startswith("root.")]
    obs[100:220, root] = False
    fill = rep.transform(truth, normalized=False)       # a model's fill: the true increments
    rf = rep._plan()["rootf"]
    px = rep.channels.index("root.tx")
    zstd = np.random.default_rng(0).uniform(0.1, 1, fill.shape)
    d0 = json.loads(json.dumps(rep.to_dict()))
    old = Representation.from_dict({k: v for k, v in d0.items() if k != "root_std"})
    assert old.root_std == []
    rep2 = Representation.from_dict(d0)
    assert rep2.root_std == rule
    reps = (rep2, old, rep.with_root_std([1.0, 1.0, 0.0, 0.0, 1.0]))
    states = [r.new_state(1) for r in reps]
    out = [[], [], []]
    for t in range(truth.shape[0]):
        f, o = np.where(obs[t], truth[t], np.nan)[None], obs[t][None]
        for st, acc in zip(states, out):
            st.encode(f, o)
            acc.append(st.finish(fill[t : t + 1], zstd[t : t + 1], f, o)[1][0, px])
    got, summed, nested = (np.array(v) for v in out)
    a, p, c, w, u = rule
    g = np.arange(1, 121, dtype=float)
    q = np.cumsum(w * np.hypot(fill[100:220, rf[0]], fill[100:220, rf[2]])
                  + u * np.maximum(zstd[100:220, rf[0]], zstd[100:220, rf[2]]))
    np.testing.assert_allclose(got[100:220], a * g ** (p - 1) * (q + c * g), rtol=1e-12)
    assert (got[:100] == 0).all() and (got[220:] == 0).all()
    assert got[219] > got[110] > 0
    np.testing.assert_allclose(nested, summed, rtol=1e-12, atol=0)
    assert not np.allclose(summed[100:220], got[100:220])
    for bad in ([1.0, 1.0, 0.0, 0.5], [0.0, 1.0, 0.1, 0.5, 0.3], [0.4, 1.0, -0.1, 0.5, 0.3], [0.4, float("nan"), 0.1, 0.5, 0.3]):
        d = rep.to_dict()
        d["root_std"] = bad
        with pytest.raises(ValueError, match="root_std"):
            Representation.from_dict(d)
