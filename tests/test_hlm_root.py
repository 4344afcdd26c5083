"""The HLM's heading-relative root (``mocap.representation``, root_mode "relative"): fills of the
body do not depend on which way the performer faces, survive turning, and a root that drops
out is integrated from where it was (no jump), damped toward holding it, with a growing std;
the faithful methods keep the paper's raw root."""
import numpy as np
import pytest

from hlm.methods import FAITHFUL_TRAIN, train_model
from mocap import splits
from mocap.baselines import HoldModel
from mocap.protocols import LEG_BONES, Gaps, TrainingSet, bone
from mocap.representation import _matrix_to_rxyz, _matrix_to_ypr, _rxyz_to_matrix

pytestmark = [pytest.mark.realdata]

TRAIN = ["35_01", "35_06", "07_02", "walking_13", "walking_22"]   # all in splits.TRAIN


@pytest.fixture(scope="module")
def model(data):
    ms = [splits.load_take(t) for t in TRAIN]
    assert all(splits.split_of(t) == "train" for t in TRAIN)
    return train_model([m.frames for m in ms], ms[0].channels, TRAIN, styles=2, restarts=1, n_iter=4,
                       screen_iters=None)


@pytest.fixture(scope="module")
def walk(data):
    m = splits.load_take("walking_20")          # a validation walk of a performer not trained on
    return m.frames[:480].copy(), m.channels


def _yaw(frames, ch):
    i = [ch.index(c) for c in ("root.rx", "root.ry", "root.rz")]
    r = np.deg2rad(frames[:, i])
    return _matrix_to_ypr(_rxyz_to_matrix(r[:, 0], r[:, 1], r[:, 2]))[0]


def turned(frames, ch, yaw_rate_deg, const_deg=0.0):
    """The same walk turned about the vertical: heading + const + rate t, and its ground-plane
    steps rotated with the heading (so the steps in the body frame are the take's own)."""
    out = frames.copy()
    rot = [ch.index(c) for c in ("root.rx", "root.ry", "root.rz")]
    pos = [ch.index(c) for c in ("root.tx", "root.ty", "root.tz")]
    a = np.deg2rad(const_deg + yaw_rate_deg * np.arange(frames.shape[0]))
    c, s = np.cos(a), np.sin(a)
    Ry = np.zeros((a.size, 3, 3))
    Ry[:, 0, 0], Ry[:, 0, 2], Ry[:, 1, 1], Ry[:, 2, 0], Ry[:, 2, 2] = c, s, 1.0, -s, c
    r = np.deg2rad(frames[:, rot])
    out[:, rot] = _matrix_to_rxyz(Ry @ _rxyz_to_matrix(r[:, 0], r[:, 1], r[:, 2]), frames[:, rot])
    step = np.diff(frames[:, pos], axis=0)
    moved = np.einsum("tij,tj->ti", Ry[1:], step)
    out[0, pos] = Ry[0] @ frames[0, pos]
    out[1:, pos] = out[0, pos] + np.cumsum(moved, axis=0)
    out[:, pos[1]] = frames[:, pos[1]]
    return out


def _occlusion(frames, ch, root_too=False):
    obs, _ = Gaps(seed=0).occlusion("walking_20", frames.shape[0], ch, 120.0)
    if root_too:
        obs[200:330, [i for i, c in enumerate(ch) if c.startswith("root.")]] = False
    return obs


def _body(ch):
    return np.array([not c.startswith("root.") for c in ch])


def test_hlm_defaults_to_the_relative_root_and_the_faithful_methods_keep_the_papers(model):
    assert model.representation.root_mode == "relative"
    assert model.representation.root_tau > 0 or model.representation.root_turn > 0  # the root is damped
    assert FAITHFUL_TRAIN["root_mode"] == "raw" and FAITHFUL_TRAIN["normalize"] is False


@pytest.mark.parametrize("root_too", [False, True])
def test_body_fill_is_invariant_to_a_constant_heading(model, walk, root_too):
    frames, ch = walk
    obs = _occlusion(frames, ch, root_too)
    moved = turned(frames, ch, 0.0, const_deg=73.0)
    assert np.abs(moved[:, ch.index("root.tx")] - frames[:, ch.index("root.tx")]).max() > 1.0
    a, _ = model.fill_offline(np.where(obs, frames, np.nan), obs)
    b, _ = model.fill_offline(np.where(obs, moved, np.nan), obs)
    body = _body(ch)
    assert (~obs[:, body]).sum() > 1000
    np.testing.assert_allclose(b[:, body], a[:, body], rtol=0, atol=1e-6)
    if root_too:
        # the filled root is the first take's filled root, turned the same way
        want = turned(a, ch, 0.0, const_deg=73.0)
        pos = [ch.index(c) for c in ("root.tx", "root.tz")]
        np.testing.assert_allclose(b[200:330, pos], want[200:330, pos], rtol=0, atol=1e-6)


def test_a_turning_walk_is_filled_as_well_as_the_straight_one(model, walk):
    """A ramp of the heading (36 degrees a second, a full turn in 10 s) changes only the yaw
    rate the model sees: the body fill stays within 15% of the straight walk's, and under hold's."""
    frames, ch = walk
    obs = _occlusion(frames, ch)
    body = _body(ch)
    ramp = turned(frames, ch, 0.3)
    assert np.ptp(np.unwrap(_yaw(ramp, ch))) > np.deg2rad(120)

    def rms(truth, fill):
        m = ~obs & body[None]
        e = (fill - truth + 180.0) % 360.0 - 180.0
        return float(np.sqrt(np.mean(e[m] ** 2)))

    straight = rms(frames, model.fill_offline(np.where(obs, frames, np.nan), obs)[0])
    turning = rms(ramp, model.fill_offline(np.where(obs, ramp, np.nan), obs)[0])
    hold = rms(ramp, HoldModel.fit([ramp], ch).fill_offline(np.where(obs, ramp, np.nan), obs)[0])
    assert turning <= 1.15 * straight, (turning, straight)
    assert turning < hold, (turning, hold)


@pytest.mark.parametrize("pattern", ["root-burst", "legs-only"])
def test_an_erased_root_starts_where_it_was_and_drifts_less_than_hold(model, walk, pattern):
    frames, ch = walk
    T = frames.shape[0]
    obs = np.ones(frames.shape, bool)
    if pattern == "legs-only":                       # pan2009's pattern: all but the legs, second half
        t0 = T // 2
        obs[t0:, ~np.array([bone(c) in LEG_BONES for c in ch])] = False
    else:
        t0 = 200
        obs[t0:330, [i for i, c in enumerate(ch) if c.startswith("root.")]] = False
    fill, std = model.fill_offline(np.where(obs, frames, np.nan), obs)
    held, _ = HoldModel.fit([frames], ch).fill_offline(np.where(obs, frames, np.nan), obs)
    pos = [ch.index(c) for c in ("root.tx", "root.ty", "root.tz")]
    gap = ~obs[:, pos[0]]

    def dist(x):
        return np.linalg.norm(x[:, pos] - frames[:, pos], axis=1)

    err, err_hold = dist(fill), dist(held)
    assert np.sqrt(np.mean(err[gap] ** 2)) <= np.sqrt(np.mean(err_hold[gap] ** 2))
    # no jump on the ground: the first erased frame is off by at most twice the performer's own
    # step (the height, absolute in the representation, is the model's fill)
    g = [pos[0], pos[2]]
    step = np.linalg.norm(frames[t0, g] - frames[t0 - 1, g])
    assert np.linalg.norm(fill[t0, g] - frames[t0, g]) <= 2.0 * step, (fill[t0, g], frames[t0, g], step)
    # the ground position's std grows over the gap
    sx = std[gap, pos[0]]
    assert sx[0] > 0 and sx[-1] > 3 * sx[0]
    assert (np.diff(sx) >= -1e-12).all()


def test_an_erased_root_keeps_walking_straight_and_is_held_when_it_was_turning(model, walk):
    """The root's damping follows the yaw rate seen before the root went missing (root_turn): over
    pan2009's pattern (all but the legs erased for 2 s) a straight walker keeps walking (near the
    undamped integration, far below hold), one who was turning at 1 deg/frame (a 43 cm circle,
    whose future heading the gap makes a guess) is held: within hold's error, below the
    undamped integration's where the turn changes (the validation takes' turnarounds).  The cost:
    on this steady synthetic circle the stream-cycle fill's own yaw rate would follow it (the
    undamped integration's error is ~3 cm), the damping holds it instead (hold's ~13 cm)."""
    frames, ch = walk
    assert model.representation.root_turn > 0
    undamped = model.with_options(root_tau=0.0, root_turn=0.0)
    pos = [ch.index(c) for c in ("root.tx", "root.tz")]
    T = frames.shape[0]
    obs = np.ones(frames.shape, bool)
    obs[T // 2 :, ~np.array([bone(c) in LEG_BONES for c in ch])] = False
    gap = ~obs[:, pos[0]]

    def rms(m, x):
        fill, _ = m.fill_offline(np.where(obs, x, np.nan), obs)
        return float(np.sqrt(np.mean(np.sum((fill[gap][:, pos] - x[gap][:, pos]) ** 2, 1))))

    held = HoldModel.fit([frames], ch)
    straight, circle = frames, turned(frames, ch, 1.0)
    assert model.with_options().representation.root_turn == model.representation.root_turn
    s, s_und, s_hold = rms(model, straight), rms(undamped, straight), rms(held, straight)
    assert s <= 1.5 * s_und + 1.0 and s < 0.5 * s_hold, (s, s_und, s_hold)
    c, c_und, c_hold = rms(model, circle), rms(undamped, circle), rms(held, circle)
    assert c <= c_hold, (c, c_und, c_hold)
    # held, not walked off: the ground travel over the gap is a small part of the straight walk's
    fill, _ = model.fill_offline(np.where(obs, circle, np.nan), obs)
    travel = np.linalg.norm(fill[gap][-1, pos] - fill[gap][0, pos])
    fill_s, _ = model.fill_offline(np.where(obs, straight, np.nan), obs)
    assert travel < 0.25 * np.linalg.norm(fill_s[gap][-1, pos] - fill_s[gap][0, pos])


def test_velocity_features_are_not_observed_right_after_a_root_gap(model, walk):
    """When the root comes back, the previous root was a fill: its displacement to the observed
    root is not an observation of one frame's motion (it would be the gap's whole error)."""
    frames, ch = walk
    rep = model.representation
    st = rep.new_state(1)
    root = np.array([c.startswith("root.") for c in ch])
    vel = [rep.features.index(f) for f in ("root.dside", "root.dfwd", "root.dyaw")]
    for t in range(60):
        o = np.ones(len(ch), bool)
        if 20 <= t < 30:
            o[root] = False
        z, zo = st.encode(np.where(o, frames[t], np.nan)[None], o[None])
        assert zo[0, vel].all() == (t < 20 or t > 30), t
        fill = np.where(zo, z, 0.0)
        st.finish(fill, np.zeros_like(fill), np.where(o, frames[t], np.nan)[None], o[None])


def test_faithful_methods_train_the_papers_representation_whatever_hlms_defaults(data, walk):
    """``hlm-faithful`` and ``hlm-faithful-offline`` keep the model as it was before the relative
    root became ``hlm``'s default: raw root, not normalised, C = 4, no adaptation; their fills
    equal a model trained with those settings spelled out."""
    from lacuna import registry

    ms = [splits.load_take(t) for t in TRAIN[:3]]
    ts = TrainingSet([m.frames for m in ms], ms[0].channels, 120.0, TRAIN[:3])
    quick = {"restarts": 1, "n_iter": 3, "screen_iters": None, "cycle_frames": 140}
    spec = registry.get_method("hlm-faithful")
    fm = spec.train(ts, **{**quick, **spec.defaults})
    assert fm.representation.root_mode == "raw" and not fm.representation.normalize
    assert fm.params.n_styles == 4 and fm.options.kappa == 0.0
    ref = train_model(ts.sequences, ts.channels, ts.names, root_mode="raw", normalize=False, styles=4, kappa=0.0,
                      kappa_global=0.0, style_switch=0.0, **quick)
    frames, ch = walk
    obs = _occlusion(frames, ch, root_too=True)
    given = np.where(obs, frames, np.nan)
    for name in ("hlm-faithful", "hlm-faithful-offline"):
        a, sa = registry.get_method(name).run(fm, given, obs.copy())
        b, sb = registry.get_method(name).run(ref, given, obs.copy())
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(sa, sb)
