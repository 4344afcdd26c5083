"""The baselines behind the Filler seam: causality, exact pass-through, save/load."""
import numpy as np
import pytest

from lacuna import modelfile
from lacuna.filler import FillerError
from mocap.baselines import HoldModel, InterpModel, NearestNeighbourModel

CH = ["root.tx", "a.rx", "b.ry", "c.rz"]


def _train(rng):
    return [rng.normal(size=(50, 4)) * [10, 20, 30, 5]]


def test_hold_keeps_last_observed_value_and_is_causal(rng):
    m = HoldModel.fit(_train(rng), CH)
    st = m.stream()
    f1 = st.step(np.array([1.0, 2, 3, 4]))
    assert not f1.filled.any() and (f1.std == 0).all()
    f2 = st.step(np.array([5.0, np.nan, 7, np.nan]))
    np.testing.assert_array_equal(f2.frame, [5, 2, 7, 4])
    assert list(f2.filled) == [False, True, False, True] and (f2.std[f2.filled] > 0).all()
    f3 = st.predict()  # a frame that never arrived
    np.testing.assert_array_equal(f3.frame, [5, 2, 7, 4])


def test_nn_recovers_a_training_frame_exactly(rng):
    seqs = _train(rng)
    m = NearestNeighbourModel.fit(seqs, CH)
    x = seqs[0][17].copy()
    obs = np.array([True, True, False, False])
    out = m.stream().step(np.where(obs, x, np.nan), obs)
    np.testing.assert_allclose(out.frame, x)


def test_interp_is_offline_and_interpolates_across_the_gap(rng):
    m = InterpModel(*[HoldModel.fit(_train(rng), CH).__dict__[k] for k in ("channels", "mean_", "std_")])
    assert not m.causal
    frames = np.tile(np.arange(10.0)[:, None], (1, 4))
    obs = np.ones((10, 4), bool)
    obs[3:7, 1] = False
    out, std = m.fill_offline(np.where(obs, frames, np.nan), obs)
    np.testing.assert_allclose(out, frames)
    assert (std[~obs] > 0).all() and (std[obs] == 0).all()


@pytest.mark.parametrize("cls", ["hold", "nn", "scaled-nn"])
def test_save_load_round_trip(rng, tmp_path, cls):
    seqs = _train(rng)
    m = HoldModel.fit(seqs, CH) if cls == "hold" else NearestNeighbourModel.fit(seqs, CH, cls == "scaled-nn")
    p = str(tmp_path / "m.npz")
    m.save(p)
    m2 = modelfile.load_model(p)
    assert type(m2) is type(m) and m2.channels == CH and m2.method == cls
    x = np.array([1.0, np.nan, 2.0, np.nan])
    a, b = m.stream().step(x), m2.stream().step(x)
    np.testing.assert_array_equal(a.frame, b.frame)


def test_wrong_width_and_non_finite_observed_values_are_refused(rng):
    st = HoldModel.fit(_train(rng), CH).stream()
    with pytest.raises(FillerError, match="4 channels"):
        st.step(np.zeros(5))
    with pytest.raises(FillerError, match="finite"):
        st.step(np.array([1.0, np.inf, 0, 0]), np.ones(4, bool))
    with pytest.raises(FillerError, match="mask"):
        st.step(np.zeros(4), np.ones(3, bool))


def test_step_batch_equals_single_steps(rng):
    seqs = _train(rng)
    for m in (HoldModel.fit(seqs, CH), NearestNeighbourModel.fit(seqs, CH)):
        frames = rng.normal(size=(6, 5, 4))
        obs = rng.random((6, 5, 4)) > 0.4
        singles = [m.stream() for _ in range(5)]
        batch = [m.stream() for _ in range(5)]
        for t in range(6):
            a = [s.step(np.where(o, f, np.nan), o) for s, f, o in zip(singles, frames[t], obs[t])]
            b = m.step_batch(batch, np.where(obs[t], frames[t], np.nan), obs[t])
            for x, y in zip(a, b):
                np.testing.assert_array_equal(x.frame, y.frame)
