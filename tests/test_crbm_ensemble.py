"""The pooled-chain CRBM ensemble (``crbm-ens``, crbm/ensemble.py): a small three-member model on
the real taylor2007 split.  The quality experiment is in test_crbm_taylor2007.py."""
from __future__ import annotations

import numpy as np
import pytest

from crbm.ensemble import CRBMEnsemble
from crbm.filler import CRBMModel
from crbm.train import MEMBER_SEED_STRIDE, train_model
from lacuna.modelfile import ModelFileError, load_arrays, load_model, save_arrays
from mocap.protocols import get_protocol


@pytest.fixture(scope="module")
def split(data):
    p = get_protocol("taylor2007")
    return p.training_set(), p.cases()


@pytest.fixture(scope="module")
def ens(split):
    ts, _ = split
    return train_model(ts.sequences, ts.channels, hidden=30, epochs=15, seed=5, members=3, n_chains=2,
                       positive_hidden="prob", method="crbm-ens")


@pytest.fixture
def walk(split):
    case = next(c for c in split[1] if c.test == "35_29" and c.erased == "right-leg")
    return case.truth[:60], case.observed[:60].copy()


def run(model, frames, observed, seed=0):
    model.reseed(seed)
    st = model.stream()
    fills = [st.step(np.where(o, f, np.nan), o) for f, o in zip(frames, observed)]
    return np.array([f.frame for f in fills]), np.array([f.std for f in fills])


def _gap(frames, obs):
    obs = obs.copy()
    obs[30:, :] = True
    obs[30:, 20:27] = False     # a 30-frame gap in seven channels
    return frames, obs


def test_members_are_distinct_seeds_and_member0_is_the_single_model(ens, split):
    ts, _ = split
    assert isinstance(ens, CRBMEnsemble) and len(ens.members) == 3
    assert [m.random_state for m in ens.members] == [5, 5 + MEMBER_SEED_STRIDE, 5 + 2 * MEMBER_SEED_STRIDE]
    assert not np.allclose(ens.members[0].W_, ens.members[1].W_)
    single = train_model(ts.sequences, ts.channels, hidden=30, epochs=15, seed=5, positive_hidden="prob")
    np.testing.assert_array_equal(single.crbm.W_, ens.members[0].W_)


def test_fill_is_the_mean_of_the_members_from_the_shared_history(ens, walk):
    """Mean-field (deterministic): one frame with missing channels, after a fully observed past,
    equals the mean of what each member alone fills from the same past."""
    frames, obs = _gap(*walk)
    ens.set_mode("mean-field")
    try:
        out, std = run(ens, frames[:31], obs[:31])
        alone = []
        for m in ens.members:
            single = CRBMModel(ens.representation, m, mode="mean-field")
            alone.append(run(single, frames[:31], obs[:31])[0][30])
    finally:
        ens.set_mode("gibbs")
    miss = ~obs[30]
    np.testing.assert_allclose(out[30, miss], np.mean(alone, 0)[miss], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(out[30, ~miss], frames[30, ~miss])
    # the std pools the members' disagreement, so it is positive where filled
    assert np.all(std[30, miss] > 0) and np.all(std[30, ~miss] == 0)


def test_clamped_exact_and_save_load_round_trip(ens, walk, tmp_path):
    frames, obs = _gap(*walk)
    a, sa = run(ens, frames, obs, seed=4)
    np.testing.assert_array_equal(a[obs], frames[obs])
    assert np.all(np.isfinite(a)) and np.all(sa[~obs] > 0)
    path = tmp_path / "ens.npz"
    ens.save(str(path))
    back = load_model(str(path))
    assert isinstance(back, CRBMEnsemble) and back.method == "crbm-ens" and len(back.members) == 3
    assert back.n_chains == 2
    b, sb = run(back, frames, obs, seed=4)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(sa, sb)
    meta, arrays = load_arrays(str(path))
    assert meta["training"]["members"] == 3
    arrays["m2_B"] = arrays["m2_B"][:, :-1]
    save_arrays(tmp_path / "bad.npz", meta, arrays)
    with pytest.raises(ModelFileError, match="array m2_B has shape"):
        load_model(str(tmp_path / "bad.npz"))


def test_batched_equals_single_streams_and_degrade_knob(ens, split):
    leg = next(c for c in split[1] if c.test == "35_29" and c.erased == "right-leg")
    body = next(c for c in split[1] if c.test == "35_29" and c.erased == "upper-body")
    T = 44
    streams = [(leg.truth[:T], leg.observed[:T]), (body.truth[:T], np.roll(body.observed[:T], -40, 0))]
    single = [run(ens, f, o)[0] for f, o in streams]
    ens.reseed(0)
    states = [ens.stream() for _ in streams]
    batched = []
    for t in range(T):
        fr = np.stack([np.where(o[t], f[t], np.nan) for f, o in streams])
        ob = np.stack([o[t] for _, o in streams])
        batched.append([x.frame for x in ens.step_batch(states, fr, ob)])
    batched = np.array(batched)
    for i in range(2):
        np.testing.assert_allclose(batched[:, i], single[i], rtol=0, atol=1e-9)
    ens.set_iterations(5)
    try:
        st = ens.stream()
        f = st.step(np.where(leg.observed[-1], leg.truth[-1], np.nan), leg.observed[-1])
        assert f.extras["gibbs_iterations"] == 5 and np.all(np.isfinite(f.frame))
    finally:
        ens.set_iterations(30)


def test_bad_members_argument_is_refused(split):
    ts, _ = split
    with pytest.raises(ValueError, match="members must be an integer >= 1"):
        train_model(ts.sequences, ts.channels, hidden=10, epochs=1, members=0)
    with pytest.raises(ValueError, match="one level only"):
        train_model(ts.sequences, ts.channels, hidden=10, epochs=1, members=2, levels=2)
