"""CRBM model and CD-1 training (issue 4, deliverables 1 and 6)."""
from __future__ import annotations

import numpy as np
import pytest

from crbm.model import CRBM
from crbm.train import train_model

D = 6


def ar_process(rng: np.random.Generator, n_seq: int, n: int) -> tuple[list[np.ndarray], np.ndarray]:
    """A known stable linear AR(1) process in D dims: x_t = x_{t-1} A^T + N(0, 0.3^2)."""
    A = 0.9 * np.eye(D) + 0.1 * rng.standard_normal((D, D))
    A *= 0.95 / np.max(np.abs(np.linalg.eigvals(A)))

    def seq() -> np.ndarray:
        x = np.zeros((n, D))
        x[0] = rng.standard_normal(D)
        for t in range(1, n):
            x[t] = x[t - 1] @ A.T + 0.3 * rng.standard_normal(D)
        return x

    return [seq() for _ in range(n_seq)], A


def test_issue4_ar_process_predicts_next_frame_better_than_mean(rng, seed):
    train, A = ar_process(rng, 10, 200)
    x = np.zeros((300, D))
    for t in range(1, 300):
        x[t] = x[t - 1] @ A.T + 0.3 * rng.standard_normal(D)
    model = train_model(train, [f"m{i}.tx" for i in range(D)], hidden=20, epochs=100, seed=seed,
                        root_mode="raw", mode="mean-field")
    mu = np.vstack(train).mean(0)
    err, base, oracle = [], [], []
    for t0 in range(10, 300, 5):
        st = model.stream()
        for f in x[t0 - 3 : t0]:
            st.step(f)
        p = st.predict().frame
        err.append(((p - x[t0]) ** 2).mean())
        base.append(((mu - x[t0]) ** 2).mean())
        oracle.append(((x[t0 - 1] @ A.T - x[t0]) ** 2).mean())
    print(f"next-frame MSE: crbm {np.mean(err):.3f}, mean {np.mean(base):.3f}, true AR {np.mean(oracle):.3f}")
    assert np.mean(err) < 0.5 * np.mean(base)
    assert np.mean(err) < 3.0 * np.mean(oracle)


def test_issue4_cd_reduces_reconstruction_error(rng, seed):
    train, _ = ar_process(rng, 5, 150)
    m = CRBM(n_hidden=16, n_epochs=30, random_state=seed)
    X = [(s - s.mean(0)) / s.std(0) for s in train]
    before = CRBM(n_hidden=16, random_state=seed).fit(X, n_epochs=0).reconstruction_error(X)
    m.fit(X)
    assert len(m.recon_errors_) == 30
    assert m.recon_errors_[-1] < 0.7 * m.recon_errors_[0]
    assert m.reconstruction_error(X) < 0.7 * before


def test_fit_is_reproducible_and_equals_partial_fit(rng):
    X = [rng.standard_normal((40, 5)) for _ in range(3)]
    a = CRBM(n_hidden=8, n_epochs=4, random_state=7).fit(X)
    b = CRBM(n_hidden=8, n_epochs=4, random_state=7).fit(X)
    c = CRBM(n_hidden=8, random_state=7)
    for _ in range(4):
        c.partial_fit(X)
    for k in ("W_", "A_", "B_", "c_", "b_"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
        np.testing.assert_array_equal(getattr(a, k), getattr(c, k))


def test_training_leaves_inputs_unmodified(rng):
    X = [rng.standard_normal((30, 4)) for _ in range(2)]
    copy = [x.copy() for x in X]
    CRBM(n_hidden=5, n_epochs=2, history_noise=1.0).fit(X)
    for x, y in zip(X, copy):
        np.testing.assert_array_equal(x, y)


def test_chunks_never_cross_sequence_boundaries(rng):
    m = CRBM(order=3)
    X, idx = m._stack([rng.standard_normal((10, 2)), rng.standard_normal((2, 2)), rng.standard_normal((6, 2))])
    # sequence starts at 0, 10, 12: a case needs its 3 past frames in its own sequence
    np.testing.assert_array_equal(idx, [3, 4, 5, 6, 7, 8, 9, 15, 16, 17])
    hist = m.history_at(X, idx[:1])
    np.testing.assert_array_equal(hist[0], np.concatenate([X[2], X[1], X[0]]))


def test_hidden_sample_mean_matches_probabilities(rng):
    m = CRBM(n_hidden=6, random_state=0).fit([rng.standard_normal((50, 3))], n_epochs=1)
    v = rng.standard_normal((1, 3))
    hist = rng.standard_normal((1, 9))
    _, bh = m.dynamic_biases(hist)
    p = m._mean_hiddens(v, bh)[0]
    s = np.mean([m._sample_hiddens(v, bh, rng)[0] for _ in range(4000)], 0)
    np.testing.assert_allclose(s, p, atol=0.03)
    assert np.all(np.isfinite(m.free_energy(v, hist)))
    assert np.all(np.isfinite(m.gibbs(v, hist, rng)))


def test_gibbs_keeps_clamped_values(rng):
    m = CRBM(n_hidden=6, random_state=0).fit([rng.standard_normal((50, 4))], n_epochs=1)
    v = rng.standard_normal((3, 4))
    clamp = np.array([[True, False, True, False]] * 3)
    out = m.gibbs(v, rng.standard_normal((3, 12)), rng, clamp=clamp)
    np.testing.assert_array_equal(out[clamp], v[clamp])


@pytest.mark.parametrize("kw, word", [({"n_hidden": 0}, "n_hidden"), ({"order": 1.5}, "order"),
                                      ({"momentum": 2.0}, "momentum"), ({"positive_hidden": "x"}, "positive_hidden"),
                                      ({"visible": "poisson"}, "visible")])
def test_bad_hyperparameters_are_refused_by_name(kw, word, rng):
    with pytest.raises(ValueError, match=word):
        CRBM(**kw).fit([rng.standard_normal((20, 3))], n_epochs=1)


def test_bad_training_data_is_refused(rng):
    with pytest.raises(ValueError, match="shorter than order"):
        CRBM(order=3).fit([rng.standard_normal((3, 2))], n_epochs=1)
    bad = rng.standard_normal((20, 2))
    bad[5, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        CRBM().fit([bad], n_epochs=1)
    m = CRBM(n_hidden=3).fit([rng.standard_normal((20, 2))], n_epochs=1)
    with pytest.raises(ValueError, match="3 features; this CRBM has 2"):
        m.partial_fit([rng.standard_normal((20, 3))])
    with pytest.raises(ValueError, match="not trained"):
        CRBM().dynamic_biases(np.zeros((1, 6)))
