"""Offline use of a trained HLM: style/phase posteriors, Viterbi alignment, purity."""
import numpy as np
import pytest

from hlm.methods import train_model
from hlm.offline import purity
from hlm.synthetic import random_cycles, sample

C, M, F = 2, 40, 6
CH = [f"j{i}.tx" for i in range(F)]


@pytest.fixture(scope="module")
def world():
    rng = np.random.default_rng(21)
    Z = random_cycles(C, M, F, rng)
    lam = np.full((C, F), 4.0)
    seqs, truth = sample(Z, lam, [100] * 8, rng, labels=np.array([0, 1] * 4))
    test, ttruth = sample(Z, lam, [90, 90], rng, labels=np.array([0, 1]))
    model = train_model(seqs, CH, styles=C, cycle_frames=M // 2, restarts=2, n_iter=8, kappa=0.0)
    return model, truth, test, ttruth


def test_posterior_and_viterbi_recover_style_and_alignment(world):
    model, truth, test, ttruth = world
    assign = np.array(model.meta["training"]["psi"]).argmax(1)
    for k in range(2):
        x = test[k]
        post = model.posterior(x)
        assert post.P.shape == (x.shape[0], C, M)
        np.testing.assert_allclose(post.P.sum(axis=(1, 2)), 1.0)
        learned = int(post.style.argmax())
        assert np.bincount(truth.labels[assign == learned]).argmax() == ttruth.labels[k]
        style, state = model.viterbi(x)
        assert (style == learned).all()                  # one style per sequence (step 4a)
        jumps = np.diff(state) % M
        assert ((jumps >= 1) & (jumps <= 3)).all()        # eq. (1): advance 1..J every frame
        # aligned to the true path up to a constant phase shift (the learned cycle's origin)
        shift = (state - ttruth.paths[k]) % M
        circ = np.angle(np.exp(2j * np.pi * (shift - np.median(shift)) / M)) * M / (2 * np.pi)
        assert np.mean(np.abs(circ) <= 2) > 0.9
        # phase is the circular mean of the state posterior, in [0, 1)
        assert ((post.phase >= 0) & (post.phase < 1)).all()


def test_offline_fill_uses_the_future_and_beats_the_causal_filter(world, rng):
    model, _, test, _ = world
    x = test[0]
    obs = np.ones(x.shape, bool)
    obs[30:60, :4] = False
    off, off_sd = model.fill_smoothed(np.where(obs, x, np.nan), obs)
    on, _ = model.fill_offline(np.where(obs, x, np.nan), obs)
    e_off = np.mean((off - x)[~obs] ** 2)
    e_on = np.mean((on - x)[~obs] ** 2)
    assert e_off <= e_on * 1.05
    np.testing.assert_array_equal(off[obs], x[obs])
    assert (off_sd[~obs] > 0).all() and (off_sd[obs] == 0).all()


def test_purity_is_the_papers_footnote_4():
    assert purity([0, 0, 1, 1], ["a", "a", "b", "b"]) == 1.0
    assert purity([0, 0, 0, 0], ["a", "a", "b", "b"]) == 0.5
    assert purity([0, 0, 0, 1], ["a", "a", "b", "b"]) == 0.75
    with pytest.raises(ValueError):
        purity([0, 1], ["a"])
