"""The faithful ``crbm`` does what Taylor's released training code and the paper's fill procedure
do (issue 17, part 4): mini-batches cut once and never crossing a sequence, the released CD-1
update (noisy history, hidden probabilities in the data term, biases initialised like the
weights), and a fill that clamps the observed channels through every Gibbs iteration and ends
with one mean-field step from the visibles the last iteration left.

Each check replays the procedure by hand with the model's own random numbers and compares
exactly, so a change in the order of any step fails it.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.special import expit

from crbm.methods import VARIANTS
from crbm.model import CRBM
from crbm.train import train_model

RELEASED = {"history_noise": 1.0, "positive_hidden": "prob", "bias_init_std": 0.01, "batches": "fixed"}


def _seq_ids(lengths):
    return np.concatenate([np.full(n, k) for k, n in enumerate(lengths)])


def test_faithful_crbm_trains_as_the_released_code(rng):
    assert not set(RELEASED) & set(VARIANTS["crbm"])        # ``crbm`` takes train_model's defaults
    seqs = [rng.standard_normal((20, 3)) for _ in range(2)]
    m = train_model(seqs, ["a.tx", "b.tx", "c.tx"], hidden=4, epochs=1, root_mode="raw").crbm
    assert {k: getattr(m, k) for k in RELEASED} == RELEASED
    assert (m.learning_rate, m.learning_rate_ar, m.weight_decay, m.momentum, m.momentum_after,
            m.batch_size, m.init_std, m.order) == (1e-3, 1e-5, 2e-4, 0.9, 5, 100, 0.01, 3)


def test_fixed_minibatches_never_cross_sequences_and_repeat_every_epoch(rng):
    lengths = [23, 4, 2, 40, 17]
    seqs = [rng.standard_normal((n, 3)) for n in lengths]
    seq = _seq_ids(lengths)
    m = CRBM(n_hidden=4, order=3, batch_size=8, batches="fixed", random_state=1)
    X, idx = m._stack(seqs)
    m._init(3)
    first = [b.copy() for b in m._epoch_batches(idx)]
    n_cases = sum(max(0, n - 3) for n in lengths)         # 20 + 1 + 0 + 37 + 14 = 72
    assert len(first) == n_cases // 8 and all(len(b) == 8 for b in first)
    used = np.concatenate(first)
    assert len(np.unique(used)) == len(used)               # no case twice in an epoch
    for i in used:                                          # its 3 past frames are in its own sequence
        assert i >= 3 and np.all(seq[i - 3 : i] == seq[i]), i
    m.partial_fit(seqs)
    m.partial_fit(seqs)
    again = m._epoch_batches(idx)
    assert all(np.array_equal(a, b) for a, b in zip(first, again))
    # "reshuffle": every case once per epoch, a new order each epoch, never crossing either
    r = CRBM(n_hidden=4, order=3, batch_size=8, batches="reshuffle", random_state=1)
    r._init(3)
    e1, e2 = np.concatenate(r._epoch_batches(idx)), np.concatenate(r._epoch_batches(idx))
    np.testing.assert_array_equal(np.sort(e1), idx)
    assert not np.array_equal(e1, e2)


def test_cd1_update_is_the_released_codes(rng):
    """One mini-batch, no momentum, replayed by hand: past frames + N(0, 1) noise set the dynamic
    biases; data term with hidden probabilities (eq. 2); reconstruction = mean visibles from
    sampled hiddens (eq. 3); rates 1e-3 (W, B, biases) and 1e-5 (A); decay 2e-4 on W, A, B only."""
    V, H, n = 4, 7, 3
    X = [rng.standard_normal((30, V))]
    m = CRBM(n_hidden=H, order=n, **RELEASED, random_state=5)
    Xs, idx = m._stack(X)
    m._init(V)
    # biases start like the weights, from N(0, 0.01^2)
    assert np.all(m.c_ != 0) and np.all(m.b_ != 0) and np.abs(np.r_[m.c_, m.b_]).max() < 0.06
    bi = idx[:10]
    v, hist = Xs[bi], m.history_at(Xs, bi)
    before = {k: getattr(m, k).copy() for k in ("W_", "A_", "B_", "c_", "b_")}
    g = np.random.default_rng()
    g.bit_generator.state = m._rng.bit_generator.state
    m._cd1(v, hist, momentum=0.0)

    W, A, B, c, b = (before[k] for k in ("W_", "A_", "B_", "c_", "b_"))
    past = hist + g.standard_normal(hist.shape)
    bv, bh = c + past @ A, b + past @ B
    ph = expit(v @ W + bh)
    hs = (g.random(ph.shape) < ph).astype(float)
    vneg = hs @ W.T + bv
    phn = expit(vneg @ W + bh)
    k = len(bi)
    want = {
        "W_": W + 1e-3 * ((v.T @ ph - vneg.T @ phn) / k - 2e-4 * W),
        "B_": B + 1e-3 * ((past.T @ ph - past.T @ phn) / k - 2e-4 * B),
        "A_": A + 1e-5 * ((past.T @ v - past.T @ vneg) / k - 2e-4 * A),
        "c_": c + 1e-3 * (v - vneg).mean(0),
        "b_": b + 1e-3 * (ph - phn).mean(0),
    }
    for key, w in want.items():
        np.testing.assert_allclose(getattr(m, key), w, rtol=0, atol=1e-12, err_msg=key)


@pytest.fixture(scope="module")
def small():
    r = np.random.default_rng(11)
    seqs = [np.cumsum(r.standard_normal((60, 5)), 0) for _ in range(3)]
    return train_model(seqs, [f"m{i}.tx" for i in range(5)], hidden=9, epochs=3, seed=2, root_mode="raw",
                       **RELEASED)


def _by_hand(model, hist, z, obs, count, final="released"):
    """The paper's fill of one frame (section 5, papers/NOTES.md), written out: previous frame +
    N(0, 0.01^2), observed channels clamped; K Gibbs iterations (binary hiddens, mean visibles);
    then the missing visibles at c* + p(h | v_K) W^T.  ``final="old"`` is the order used before
    2026-12-01 (probabilities from the K-th iteration's input)."""
    c = model.crbm
    F = c.n_visible_
    noise, L, _ = model._draws(np.array([count]), 1, c.n_hidden, model.knobs())
    bv, bh = c.c_ + hist @ c.A_, c.b_ + hist @ c.B_
    v = np.where(obs, z, hist[:F] + model.init_noise * noise[0])
    for it in range(model.n_gibbs):
        a = v @ c.W_ + bh
        h = (a > L[it, 0]).astype(float)
        v = np.where(obs, z, h @ c.W_.T + bv)
    ph = expit(v @ c.W_ + bh) if final == "released" else expit(a)
    return np.where(obs, z, ph @ c.W_.T + bv)


@pytest.mark.parametrize("K", [1, 4, 30])
def test_fill_clamps_observed_channels_throughout_and_ends_with_mean_field(small, K):
    model = small
    model.set_iterations(K)
    try:
        F = model.crbm.n_visible_
        r = np.random.default_rng(K)
        hist = r.standard_normal(3 * F)
        z = r.standard_normal((2, F))
        obs = np.array([[True, False, True, False, True], [False, True, True, True, False]])
        for rows in ([0], [0, 1]):                # one mask (the fast path) and two different masks
            st = model.core_init(len(rows))
            st["hist"][:] = hist
            st["count"][:] = 7
            out = model.core_step(st, np.where(obs[rows], z[rows], np.nan), obs[rows]).z
            for j, row in enumerate(rows):
                want = _by_hand(model, hist, z[row], obs[row], 7)
                np.testing.assert_allclose(out[j], want, rtol=0, atol=1e-10)
                np.testing.assert_array_equal(out[j, obs[row]], z[row, obs[row]])
                old = _by_hand(model, hist, z[row], obs[row], 7, final="old")
                assert not np.allclose(out[j][~obs[row]], old[~obs[row]], atol=1e-6)
            # the order the improved variants keep (crbm.filler.FINAL_STEPS)
            model.final_step = "input"
            try:
                st = model.core_init(len(rows))
                st["hist"][:] = hist
                st["count"][:] = 7
                out = model.core_step(st, np.where(obs[rows], z[rows], np.nan), obs[rows]).z
            finally:
                model.final_step = "last"
            for j, row in enumerate(rows):
                np.testing.assert_allclose(out[j], _by_hand(model, hist, z[row], obs[row], 7, final="old"),
                                           rtol=0, atol=1e-10)
    finally:
        model.set_iterations(30)


def test_final_step_is_kept_by_model_files_and_by_the_variants(small, tmp_path):
    from crbm.persist import load

    assert all(VARIANTS[m]["final_step"] == "input" for m in ("crbm-imp", "crbm-ens", "crbm-mf", "crbm-2level"))
    assert "final_step" not in VARIANTS["crbm"] and small.final_step == "last"
    small.save(tmp_path / "m.npz")
    assert load(tmp_path / "m.npz").final_step == "last"
    with pytest.raises(ValueError, match="final_step"):
        type(small)(small.representation, small.crbm, final_step="first")


def test_a_model_saved_by_the_released_code_loads_with_its_past_in_our_order(rng, tmp_path):
    """crbm.anchor.load_octave_model: the released code's past is [v_{t-n} ... v_{t-1}] (oldest
    first); loaded, our dynamic biases from our newest-first history equal the released ones."""
    import scipy.io

    from crbm.anchor import load_octave_model

    F, H, n = 4, 5, 3
    arrays = {"vishid": rng.standard_normal((F, H)).astype(np.float32), "pastvis": rng.standard_normal((n * F, F)),
              "pasthid": rng.standard_normal((n * F, H)), "visbiases": rng.standard_normal((1, F)),
              "hidbiases": rng.standard_normal((1, H)), "keep": np.arange(1, F + 1)[None], "nt": np.array([[n]])}
    scipy.io.savemat(tmp_path / "m.mat", arrays)
    c = load_octave_model(tmp_path / "m.mat")
    frames = rng.standard_normal((n, F))                      # v_{t-3}, v_{t-2}, v_{t-1}
    past_released = frames.reshape(1, -1)                      # reshape(V(tt-nt:tt-1,:)', 1, [])
    ours = frames[::-1].reshape(1, -1)                         # newest first
    bv, bh = c.dynamic_biases(ours)
    np.testing.assert_allclose(bv, arrays["visbiases"] + past_released @ arrays["pastvis"], atol=1e-12)
    np.testing.assert_allclose(bh, arrays["hidbiases"] + past_released @ arrays["pasthid"], atol=1e-12)
    np.testing.assert_allclose(c.W_, arrays["vishid"], atol=0)


def test_the_anchor_input_is_the_raw_split_z_scored(data):
    from crbm.anchor import anchor_data

    d = anchor_data()
    Z = np.vstack(d["sequences"])
    assert Z.shape == (2644, 56) and len(d["sequences"]) == 31           # six constant channels out
    np.testing.assert_allclose(Z.mean(0), 0, atol=1e-9)
    np.testing.assert_allclose(Z.std(0), 1, atol=1e-9)
    assert {k: v.shape[0] for k, v in d["tests"].items()} == {"35_18": 44, "35_29": 125}
