"""HLM numerics against dense references: the cyclic systems of Q(Z) and eq. (17), and the banded
log-space forward-backward / Viterbi of eq. (1) against brute-force enumeration of paths."""
import itertools

import numpy as np
import pytest

from hlm import cyclic, hmm


def test_cyclic_factor_matches_dense_inverse(rng):
    M, B = 9, 6
    s = rng.uniform(0.1, 2.0, B)
    a = 2 * s + rng.uniform(0.01, 3.0, (M, B))
    f = cyclic.factor(a, s)
    A = cyclic.dense(a, s)
    Ai = np.linalg.inv(A)
    diag, sup = f.marginals()
    idx = np.arange(M)
    np.testing.assert_allclose(diag.T, Ai[:, idx, idx], rtol=1e-10)
    np.testing.assert_allclose(sup.T, Ai[:, idx, (idx + 1) % M], rtol=1e-10, atol=1e-14)
    b = rng.normal(size=(M, B))
    np.testing.assert_allclose(f.solve(b).T, np.linalg.solve(A, b.T[..., None])[..., 0], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(f.logdet(), np.linalg.slogdet(A)[1], rtol=1e-12)


def test_cyclic_rejects_tiny_cycles():
    with pytest.raises(ValueError, match="at least 3 states"):
        cyclic.factor(np.ones((2, 1)), 0.1)


def _brute(le, ls, d):
    T, M = le.shape
    J = len(d)
    Z, G, JJ = 0.0, np.zeros((T, M)), np.zeros(J)
    best, bestp = -np.inf, None
    for path in itertools.product(range(M), repeat=T):
        lp = ls[path[0]] + le[0, path[0]]
        js = []
        for t in range(1, T):
            j = (path[t] - path[t - 1]) % M
            if not 1 <= j <= J:
                lp = -np.inf
                break
            lp += np.log(d[j - 1]) + le[t, path[t]]
            js.append(j)
        if not np.isfinite(lp):
            continue
        p = np.exp(lp)
        Z += p
        for t in range(T):
            G[t, path[t]] += p
        for j in js:
            JJ[j - 1] += p
        if lp > best:
            best, bestp = lp, path
    return np.log(Z), G / Z, JJ / Z, best, np.array(bestp)


def test_forward_backward_matches_enumeration(rng):
    T, K, M, J = 5, 3, 6, 3
    lengths = np.array([5, 3, 4])
    le = rng.normal(size=(T, K, M))
    for k in range(K):
        le[lengths[k]:, k] = 0.0      # padding convention
    ls = np.log(rng.dirichlet(np.ones(M), size=K))
    d = rng.dirichlet(np.ones(J), size=K)
    G, lz, jumps = hmm.forward_backward(le, ls, np.log(d), lengths)
    for k in range(K):
        n = lengths[k]
        bz, bG, bJ, _, _ = _brute(le[:n, k], ls[k], d[k])
        assert lz[k] == pytest.approx(bz, abs=1e-10)
        np.testing.assert_allclose(G[:n, k], bG, atol=1e-12)
        assert np.all(G[n:, k] == 0)
        np.testing.assert_allclose(jumps[k], bJ, atol=1e-10)
    # the general posteriors() helper (used with joint (style, phase) states) agrees
    G2, lz2, j2 = hmm.posteriors(hmm.forward(le, ls, np.log(d)), hmm.backward(le, np.log(d)), le, np.log(d), lengths)
    np.testing.assert_allclose(G2, G, atol=1e-12)
    np.testing.assert_allclose(lz2, lz)
    np.testing.assert_allclose(j2, jumps, atol=1e-12)


def test_viterbi_matches_enumeration(rng):
    T, M, J = 5, 6, 3
    le = rng.normal(size=(T, M))
    ls = np.log(np.full(M, 1.0 / M))
    d = rng.dirichlet(np.ones(J))
    path, lp = hmm.viterbi(le, ls, np.log(d))
    _, _, _, best, bestp = _brute(le, ls, d)
    assert lp == pytest.approx(best)
    np.testing.assert_array_equal(path[:, 0], bestp)


def test_forward_never_builds_the_transition_matrix(rng):
    # a long cycle: a dense M x M transition would be 4e8 entries; the banded pass is instant
    M = 20000
    le = rng.normal(size=(4, 1, M))
    la = hmm.forward(le, np.full((1, M), -np.log(M)), np.log(np.array([[0.2, 0.5, 0.3]])))
    assert np.isfinite(la).all()


def test_emission_tables_match_the_expected_gaussian_loglik(rng):
    from hlm.emissions import EmissionTables

    C, M, F = 3, 7, 4
    mu = rng.normal(size=(C, M, F))
    var = rng.uniform(0.01, 0.5, (C, M, F))
    lam = rng.uniform(0.5, 3.0, (C, F))
    x = rng.normal(size=(5, F))
    obs = rng.random((5, F)) > 0.4
    got = EmissionTables.build(mu, var, lam).loglik(np.where(obs, x, np.nan), obs)
    for i in range(5):
        o = obs[i]
        want = (0.5 * np.log(lam[:, None, o] / (2 * np.pi))
                - 0.5 * lam[:, None, o] * ((x[i, o] - mu[:, :, o]) ** 2 + var[:, :, o])).sum(-1)
        np.testing.assert_allclose(got[i], want, rtol=1e-12, atol=1e-12)
