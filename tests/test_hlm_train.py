"""Variational EM on data drawn from the HLM's own generative process (issue 3, item 5)."""
import warnings

import numpy as np
import pytest

from hlm import cyclic
from hlm.offline import purity
from hlm.synthetic import random_cycles, sample
from hlm.train import BoundWarning, VariationalEM, fit

C, M, F = 2, 40, 6


@pytest.fixture(scope="module")
def synth():
    rng = np.random.default_rng(7)
    Z = random_cycles(C, M, F, rng)
    lam = np.full((C, F), 4.0)
    seqs, truth = sample(Z, lam, [100, 90, 110, 100, 95, 105, 100, 100], rng, labels=np.array([0, 1] * 4))
    return seqs, truth


def test_bound_never_decreases_at_any_step(synth):
    seqs, _ = synth
    em = VariationalEM(seqs, C, M // 2, seed=3)
    b = [em.bound()]
    for _ in range(6):
        for step in (em._update_Z, em._update_l, em._update_pi, em._update_Z, em._update_l, em._update_pi, em._m_step):
            step()
            b.append(em.bound())
    d = np.diff(b)
    assert (d >= -1e-8 * np.abs(b[1:])).all(), f"bound went down: {d.min()}"
    assert b[-1] > b[0] + 100  # and it actually climbs


def test_em_iterations_raise_the_bound_and_do_not_warn(synth):
    seqs, _ = synth
    em = VariationalEM(seqs, C, M // 2, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error", BoundWarning)
        bounds = em.fit(n_iter=8, n_var=3, tol=0.0)
    assert len(bounds) == 8
    assert np.all(np.diff(bounds) >= -1e-9 * np.abs(bounds[1:]))


def test_training_recovers_styles_and_cycles(synth):
    seqs, truth = synth
    res = fit(seqs, C, M // 2, n_restarts=3, seed=0)
    assign = res.psi.argmax(1)
    assert purity(assign, truth.labels) == 1.0
    assert len(set(assign)) == C
    for c in range(C):
        true_c = np.bincount(truth.labels[assign == c]).argmax()
        Zt = truth.Z[true_c]
        # up to a phase shift of the cycle
        err = min(np.sqrt(np.mean((np.roll(res.params.mu[c], s, 0) - Zt) ** 2)) for s in range(M))
        assert err < 0.2 * np.sqrt(np.mean(Zt ** 2)), err   # noise sd is 0.5, signal rms ~2.2
    # noise precision near the truth (4.0), transition probabilities near the sampled d^k
    assert np.median(res.params.lam) == pytest.approx(4.0, rel=0.3)
    np.testing.assert_allclose(res.params.d, truth.d, atol=0.2)


def test_restarts_keep_the_best_bound(synth):
    seqs, _ = synth
    res = fit(seqs, C, M // 2, n_restarts=3, seed=10, n_iter=4, screen_iters=2)
    assert res.bounds[1] == pytest.approx(max(res.restart_bounds))
    assert res.seed == 10 + int(np.argmax(res.restart_bounds))


def test_q_z_update_is_eq9_solved_densely(synth):
    """The cyclic solver's Q(z^{c,f}) equals the dense solution of the precision derived from eq. (9)."""
    seqs, _ = synth
    em = VariationalEM(seqs, C, M // 2, seed=0)
    em._update_Z()
    W, R = em._stats()
    c, f = 1, 2
    a = 2 * em.lam_s + em.lam_zbar + em.lam[c, f] * W[c]
    S = cyclic.dense(a[:, None], em.lam_s)[0]
    mu = np.linalg.solve(S, em.lam_zbar * em.zbar[:, f] + em.lam[c, f] * R[c, :, f])
    np.testing.assert_allclose(em.mu[c, :, f], mu, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(em.var[c, :, f], np.diag(np.linalg.inv(S)), rtol=1e-9)


def test_parent_cycle_solves_corrected_eq17(synth):
    seqs, _ = synth
    em = VariationalEM(seqs, C, M // 2, seed=0)
    em.e_step(1)
    em._m_step()
    zb, eta, lz = em.zbar, em.eta, em.lam_zbar
    # gradient of <L> + P in zbar_m: lam_zbar sum_c (mu_m^c - zbar_m) + eta (2 zbar_{m-1} - 4 zbar_m + 2 zbar_{m+1})
    g = lz * (em.mu.sum(0) - C * zb) + eta * (2 * np.roll(zb, 1, 0) - 4 * zb + 2 * np.roll(zb, -1, 0))
    assert np.abs(g).max() < 1e-9


def test_missing_training_entries_are_filled_by_eq18(synth):
    seqs, truth = synth
    rng = np.random.default_rng(0)
    holed = [s.copy() for s in seqs]
    for s in holed:
        s[rng.random(s.shape) < 0.1] = np.nan
    res = fit(holed, C, M // 2, n_restarts=2, seed=0, n_iter=8)
    assert purity(res.psi.argmax(1), truth.labels) == 1.0
    err = np.concatenate([(f - s)[np.isnan(h)] for f, s, h in zip(res.filled, seqs, holed)])
    noise_sd = 0.5
    assert np.sqrt(np.mean(err ** 2)) < 1.5 * noise_sd   # about the emission noise, not the signal (~2.5)


def test_bad_training_input_is_rejected():
    with pytest.raises(ValueError, match="shape"):
        VariationalEM([np.zeros((10, 3)), np.zeros((10, 4))], 2, 10)
    with pytest.raises(ValueError, match="too few"):
        VariationalEM([np.zeros((10, 3))], 2, 2)
    with pytest.raises(ValueError, match="no training sequences"):
        VariationalEM([], 2, 10)


def test_a_coordinate_constant_within_a_style_keeps_the_bound_finite(synth):
    """A channel that moves in one style's takes only (CMU's lfingers.rx moves in 3 of 45 walks)
    has a residual of ~0 in the other style: eq. (14) must not divide by it."""
    seqs, _ = synth
    seqs = [s.copy() for s in seqs]
    for s in seqs[::2]:  # the fixture's style-0 takes (labels 0, 1, 0, 1, ...)
        s[:, 0] = 1.25
    em = VariationalEM(seqs, C, M // 2, seed=3)
    for _ in range(15):  # the paper's iteration count; uncapped, lambda reached 4e302 on the 15th
        for step in (em._update_Z, em._update_l, em._update_pi, em._m_step):
            step()
    assert np.isfinite(em.bound()) and np.isfinite(em.lam).all()
    assert em.lam.max() < 1e12 and (em.lam == em.lam_max).any()  # the cap is what held it
