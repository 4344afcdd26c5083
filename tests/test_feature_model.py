"""FeatureModel plumbing with the simplest real core: missing features become the training mean
(zero in normalised units).  Observed channels pass through exactly; batch == single streams."""
import numpy as np
import pytest

from mocap.datasets import load_trial
from mocap.feature_model import CoreOut, FeatureModel
from mocap.representation import Representation


class MeanModel(FeatureModel):
    method = "mean-test"

    def __init__(self, rep):
        self.representation = rep

    def core_init(self, n):
        return {"t": np.zeros((n, 1))}

    def core_step(self, state, z, zobs):
        state["t"] += 1
        return CoreOut(np.where(zobs, z, 0.0), np.where(zobs, 0.0, 1.0), [{"t": float(x)} for x in state["t"][:, 0]])


@pytest.fixture(scope="module")
def model(data):
    ms = [load_trial(t) for t in ("07_02", "35_01")]
    return MeanModel(Representation.fit([m.frames for m in ms], ms[0].channels))


def test_observed_pass_through_and_missing_filled(model):
    m = load_trial("07_01")
    st = model.stream()
    obs = np.ones(62, bool)
    for t in range(20):
        if t >= 10:
            obs = np.array([not c.startswith(("lhumerus", "lradius")) for c in m.channels])
        fill = st.step(np.where(obs, m.frames[t], np.nan), obs)
        assert np.array_equal(fill.frame[obs], m.frames[t][obs])
        assert np.isfinite(fill.frame).all()
        assert np.array_equal(fill.filled, ~obs)
        assert (fill.std[obs] == 0).all() and (fill.std[~obs] > 0).all()
        assert fill.extras["t"] == t + 1


def test_step_batch_equals_single_streams(model, rng):
    m = load_trial("07_01")
    singles = [model.stream() for _ in range(3)]
    batch = [model.stream() for _ in range(3)]
    for t in range(30):
        frames = np.stack([m.frames[t + 5 * i] for i in range(3)])
        obs = rng.random((3, 62)) > 0.3
        obs[:, :6] = t == 0 or obs[:, :6]
        a = [s.step(np.where(o, f, np.nan), o) for s, f, o in zip(singles, frames, obs)]
        b = model.step_batch(batch, np.where(obs, frames, np.nan), obs)
        for x, y in zip(a, b):
            np.testing.assert_allclose(x.frame, y.frame, rtol=0, atol=1e-12)
            np.testing.assert_allclose(x.std, y.std)


def test_prediction_step_and_wrong_width(model):
    st = model.stream()
    f = st.predict()
    assert f.filled.all() and np.isfinite(f.frame).all()
    from lacuna.filler import FillerError

    with pytest.raises(FillerError, match="62 channels"):
        st.step(np.zeros(61))


def test_fully_observed_frames_come_back_unchanged(model):
    m = load_trial("35_29")
    st = model.stream()
    for t in range(50):
        fill = st.step(m.frames[t])
        assert np.array_equal(fill.frame, m.frames[t]) and not fill.filled.any()


def test_state_pool_grows_reuses_freed_slots_and_starts_them_fresh(model):
    """Streams own rows of the model's state pool: the pool grows past its first capacity without
    disturbing live streams, a stream that is dropped frees its row, and the next stream takes the
    lowest free row starting from the initial state, not the previous owner's."""
    m = load_trial("07_01")
    pool = model.pool
    before = pool.in_use
    streams = [model.stream() for _ in range(10)]      # more than the first capacity of 4
    assert pool.capacity >= before + 10 and pool.in_use == before + 10
    for t in range(5):
        fills = model.step_batch(streams, np.stack([m.frames[t]] * 10), np.ones((10, 62), bool))
        assert [f.extras["t"] for f in fills] == [t + 1] * 10
    freed = streams[3].slot
    del streams[3]
    assert pool.in_use == before + 9
    fresh = model.stream()
    assert fresh.slot == freed
    assert fresh.step(m.frames[0]).extras["t"] == 1             # the old owner's count is gone
    assert streams[4].step(m.frames[5]).extras["t"] == 6        # neighbours untouched
    with pytest.raises(ValueError, match="same stream twice"):
        model.step_batch([fresh, fresh], np.stack([m.frames[0]] * 2), np.ones((2, 62), bool))
