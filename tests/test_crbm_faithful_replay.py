"""The faithful ``crbm`` and Taylor's released code on the same random numbers (issue 17, part 4).

Two ways, stage by stage:
* always: the released code's training batch (``mixgaussiancrbm.m``, one component) and the
  anchor's fill loop (``crbmfill.m``) transcribed here line for line from its equations (past
  oldest first, three noise blocks, hidden states by ``p > rand``), fed the same draws as our
  ``CRBM`` and ``CRBMModel``: the parameters after several epochs (momentum included) and every
  filled value agree to rounding;
* where Octave and the released files are present (``$LACUNA_IMCRBM``, see crbm/replay.py):
  the released code itself runs in Octave with its draws recorded, and ours replays them.
"""
from __future__ import annotations

import os
import shutil
import subprocess

import numpy as np
import pytest
from scipy.special import expit

from crbm import anchor, replay
from crbm.model import CRBM
from crbm.released import RELEASED


def _released_epoch(P, inc, Z, minibatch, draws, momentum, nt):
    """One epoch of mixgaussiancrbm.m (numcomp = 1, cdsteps = 1, gsd = 1, sparsehid = 0)."""
    eps_w = eps_vb = eps_hb = eps_b = 1e-3
    eps_a, wdecay = 1e-5, 2e-4
    F = Z.shape[1]
    for mb in minibatch:
        n = len(mb)
        data = Z[mb]
        past = np.zeros((n, nt * F))
        for hh in range(nt, 0, -1):                    # "for hh=nt:-1:1 %note reverse order"
            past[:, F * (nt - hh) : F * (nt - hh + 1)] = Z[mb - hh] + next(draws)
        effvis = P["vb"] + past @ P["A"]
        effhid = P["hb"] + past @ P["B"]
        poshid = expit(data @ P["W"] + effhid)
        hidstates = (poshid > next(draws)).astype(float)
        negdata = hidstates @ P["W"].T + effvis
        neghid = expit(negdata @ P["W"] + effhid)
        G = {"W": (data.T @ poshid - negdata.T @ neghid) / n - wdecay * P["W"],
             "vb": (data.sum(0) - negdata.sum(0)) / n, "hb": (poshid.sum(0) - neghid.sum(0)) / n,
             "A": (past.T @ data - past.T @ negdata) / n - wdecay * P["A"],
             "B": (past.T @ poshid - past.T @ neghid) / n - wdecay * P["B"]}
        eps = {"W": eps_w, "vb": eps_vb, "hb": eps_hb, "A": eps_a, "B": eps_b}
        for k in P:
            inc[k] = momentum * inc[k] + eps[k] * G[k]
        for k in P:
            P[k] = P[k] + inc[k]


def test_our_training_is_the_released_batch_update_on_the_same_draws():
    rng = np.random.default_rng(3)
    F, H, nt, epochs = 5, 7, 3, 7                        # 7 epochs: momentum starts at the 6th
    seqs = [np.cumsum(rng.standard_normal((n, F)), 0) * 0.3 for n in (40, 33, 29)]
    # the algebra in double precision (the released code's single precision: the Octave test below)
    ours = CRBM(n_hidden=H, order=nt, batch_size=10, **{**RELEASED, "dtype": "float64"})
    ours._init(F)
    Z, idx = ours._stack(seqs)
    P = {"W": ours.W_.copy(), "vb": ours.c_.copy(), "hb": ours.b_.copy(), "A": ours.A_[replay._reverse_blocks(nt, F)].copy(),
         "B": ours.B_[replay._reverse_blocks(nt, F)].copy()}
    inc = {k: np.zeros_like(v) for k, v in P.items()}
    perm = rng.permutation(idx)
    mbs = [perm[b * 10 : (b + 1) * 10] for b in range(len(idx) // 10)]
    assert len(idx) % 10 and len(mbs) == len(idx) // 10    # a remainder, left unused as there
    normals = [rng.standard_normal((10, F)) for _ in range(3 * len(mbs) * epochs)]
    uniforms = [rng.random((10, H)) for _ in range(len(mbs) * epochs)]
    order = iter([x for b in range(len(mbs) * epochs) for x in (*normals[3 * b : 3 * b + 3], uniforms[b])])
    for e in range(epochs):
        _released_epoch(P, inc, Z, mbs, order, 0.9 if e + 1 > 5 else 0.0, nt)   # "if epoch > 5"
    ours._batches, ours._batch_cases = mbs, idx
    ours._rng = replay._Recorded(normals, uniforms)
    for _ in range(epochs):
        ours.partial_fit(seqs)
    rows = replay._reverse_blocks(nt, F)
    for k, theirs in (("W_", P["W"]), ("c_", P["vb"]), ("b_", P["hb"]), ("A_", P["A"]), ("B_", P["B"])):
        mine = getattr(ours, k)[rows] if k in ("A_", "B_") else getattr(ours, k)
        np.testing.assert_allclose(mine, theirs, rtol=0, atol=1e-12, err_msg=k)
    assert np.abs(ours.W_ - ours._inc["W_"]).max() > 0      # it did train


def _released_fill(W, A, B, bv, bh, Zt, miss, st, nframes, normals, uniforms, nt, K=30):
    """crbmfill.m's loop: previous frame + 0.01 noise, observed clamped, K Gibbs iterations
    (sampled hiddens, mean visibles), a final mean-field step; history from the fill."""
    V = Zt.copy()
    V[st:, miss] = 0.0
    obs = np.setdiff1d(np.arange(Zt.shape[1]), miss)
    u = iter(uniforms)
    for t, noise in zip(range(st, st + nframes), normals):
        v = V[t - 1] + 0.01 * noise
        v[obs] = Zt[t, obs]
        past = V[t - nt : t].reshape(-1)                  # reshape(V(tt-nt:tt-1,:)', 1, [])
        ev, eh = bv + past @ A, bh + past @ B
        for _ in range(K):
            h = (expit(v @ W + eh) > next(u)).astype(float)
            v[miss] = (h @ W.T + ev)[miss]
        v[miss] = (expit(v @ W + eh) @ W.T + ev)[miss]
        V[t] = v
    return V[st : st + nframes, miss]


def test_our_fill_is_the_released_fill_loop_on_the_same_draws():
    rng = np.random.default_rng(5)
    F, H, nt, T, st, nf = 6, 9, 3, 30, 15, 8
    c = CRBM(n_hidden=H, order=nt, bias_init_std=0.3, init_std=0.3)
    c._init(F)
    c.A_ *= 0.2
    Zt = np.cumsum(rng.standard_normal((T, F)), 0) * 0.2
    miss = np.array([1, 4])
    normals = [rng.standard_normal(F) for _ in range(nf)]
    uniforms = [rng.random(H) for _ in range(nf * 30)]
    rows = replay._reverse_blocks(nt, F)
    want = _released_fill(c.W_, c.A_[rows], c.B_[rows], c.c_, c.b_, Zt, miss, st, nf, normals, uniforms, nt)
    model = anchor.filler(c)
    frames = iter(range(nf))

    def draws(counts, S, H_, kn=None):
        i = next(frames)
        u = np.stack([uniforms[i * 30 + k].reshape(1, -1) for k in range(30)])
        return normals[i].reshape(1, -1), np.log(u) - np.log1p(-u), None

    model._draws = draws
    obs = np.ones(F, bool)
    obs[miss] = False
    state, got = model.core_init(1), []
    for t in range(st + nf):
        o = obs if t >= st else np.ones(F, bool)
        got.append(model.core_step(state, np.where(o, Zt[t], np.nan)[None], o[None]).z[0])
    np.testing.assert_allclose(np.asarray(got)[st:, miss], want, rtol=0, atol=1e-10)
    assert np.abs(want - Zt[st : st + nf][:, miss]).max() > 1e-3    # it filled, not copied


octave = pytest.mark.skipif(shutil.which("octave") is None or replay.released_dir() is None,
                            reason="needs Octave and $LACUNA_IMCRBM (a directory with the released "
                                   "mixgaussiancrbm.m and crbmfe.m of github:gwtaylor/imCRBM)")


@pytest.mark.realdata
@octave
def test_the_released_code_in_octave_and_ours_agree_on_its_draws(data, tmp_path):
    """7 epochs of the released training (momentum from the 6th), then 10 frames of its leg fill
    of 35_29 on that model: ours on the recorded draws gives the same numbers to float32 rounding
    (the released code computes in single precision)."""
    env = {"DATA": str(data), "SEED": "1", "EPOCHS": "7", "NUMHID": "20", "OUT": str(tmp_path / "train.mat")}
    replay.run_octave(tmp_path, "train_replay.m", replay.OCTAVE_TRAIN, env, replay.released_dir())
    seqs = anchor.anchor_data(data)["sequences"]
    ours, theirs, dump = replay.replay_training(tmp_path / "train.mat", seqs)
    np.testing.assert_allclose(np.vstack(seqs), dump["Z"], atol=1e-12)        # the same input
    for k in ("W_", "A_", "B_", "c_", "b_"):
        d = np.abs(getattr(ours, k) - getattr(theirs, k)).max()
        assert d < 1e-5 * np.abs(getattr(theirs, k)).max(), (k, d)
    # the streams regenerated without training (bench/crbm_released_draws.py's) are the same draws
    env = {"DATA": str(data), "SEED": "1", "EPOCHS": "7", "NUMHID": "20", "OUT": str(tmp_path / "streams")}
    (tmp_path / "streams.m").write_text(replay.OCTAVE_STREAMS)
    subprocess.run(["octave", "--no-gui", "-q", "streams.m"], cwd=tmp_path, env={**os.environ, **env}, check=True,
                   capture_output=True, timeout=600)
    again = replay.train_on_streams(tmp_path / "streams", seqs)
    for k in ("W_", "A_", "B_", "c_", "b_"):
        d = np.abs(getattr(again, k) - getattr(theirs, k)).max()
        assert d < 1e-5 * np.abs(getattr(theirs, k)).max(), (k, d)
    env = {"DATA": str(data), "MODEL": str(tmp_path / "train.mat"), "SEQ": "2", "GROUP": "1", "FRAMES": "10",
           "OUT": str(tmp_path / "fill.mat")}
    replay.run_octave(tmp_path, "fill_replay.m", replay.OCTAVE_FILL, env, replay.released_dir())
    mine, octave_fill = replay.replay_fill(tmp_path / "train.mat", tmp_path / "fill.mat")
    assert mine.shape == (10, 7)
    np.testing.assert_allclose(mine, octave_fill, rtol=0, atol=1e-9)


def test_single_precision_training_as_the_released_code_returns_double_parameters():
    """mixgaussiancrbm.m trains in single; crbmfill.m fills with double(M.vishid): ours trains in
    float32 under RELEASED and hands float64 to the filler; the same seed in float64 stays close."""
    rng = np.random.default_rng(8)
    seqs = [np.cumsum(rng.standard_normal((60, 4)), 0) * 0.2 for _ in range(3)]
    seen = []
    m32 = CRBM(n_hidden=6, order=3, n_epochs=4, batch_size=20, random_state=2, **RELEASED,
               progress=lambda e, err: seen.append(m32.W_.dtype))
    m32.fit(seqs)
    assert RELEASED["dtype"] == "float32" and set(seen) == {np.dtype(np.float32)}
    assert all(getattr(m32, k).dtype == np.float64 for k in ("W_", "A_", "B_", "c_", "b_"))
    m64 = CRBM(n_hidden=6, order=3, n_epochs=4, batch_size=20, random_state=2, **{**RELEASED, "dtype": "float64"}).fit(seqs)
    d = np.abs(m32.W_ - m64.W_).max()
    assert 0 < d < 1e-5, d        # the same draws, single-precision rounding only
