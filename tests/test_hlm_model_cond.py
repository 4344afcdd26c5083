"""The HLM's conditional fill (hlm.condfill): the missing features given the observed ones'
residuals about the stream's own cycle.

Real motion: an HLM trained on three subject-35 walks follows a held-out walk with an arm missing
in bursts (few missing: the precision-matrix solve) and everything but the legs missing over its
second half (pan2009's pattern: the covariance solve); the compiled correction (the daemon's
single-stream step and the batched step) must equal the numpy reference to 1e-9, the two solves
must agree, the faithful methods and files written before it must fill as eq. (18) alone."""
from __future__ import annotations

import numpy as np
import pytest

from hlm import condfill, fast
from hlm.methods import FAITHFUL, train_model


@pytest.fixture(scope="module")
def walk(data):
    from mocap.datasets import load_trial

    train = [load_trial(t) for t in ("35_01", "35_06", "35_07")]
    channels = train[0].channels
    model = train_model([m.frames for m in train], channels, n_iter=3, restarts=1, styles=2, cond_shrink=1.0)
    test = load_trial("35_08").frames[:300]
    obs = np.ones(test.shape, bool)
    arm = [i for i, c in enumerate(channels) if c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "lhand")]
    for start in (20, 100):
        obs[start : start + 50, arm] = False
    legs = np.array([c.split(".")[0] in ("lfemur", "ltibia", "lfoot", "ltoes", "rfemur", "rtibia", "rfoot", "rtoes")
                     for c in channels])
    obs[180:, ~legs] = False
    return model, test, obs


def _run(model, frames, obs, monkeypatch, jit: bool, batch: bool = False):
    monkeypatch.setenv("LACUNA_NO_JIT", "0" if jit else "1")
    s = model.stream()
    out = []
    for t in range(frames.shape[0]):
        f = np.where(obs[t], frames[t], np.nan)
        fill = model.step_batch([s], f[None], obs[t][None])[0] if batch else s.step(f, obs[t])
        out.append((fill.frame.copy(), fill.std.copy()))
    return np.array([a for a, _ in out]), np.array([b for _, b in out])


def test_training_fits_a_covariance_with_the_root_apart(walk):
    model, _, _ = walk
    cov = model.cond_cov
    rep = model.representation
    F = rep.n_features
    C = model.params.n_styles
    assert cov.shape == (C, F, F) and np.allclose(cov, cov.transpose(0, 2, 1)) and np.linalg.eigvalsh(cov).min() > 0
    root = np.array([f.startswith("root.") for f in rep.features])
    assert root.any() and (cov[:, root][:, :, ~root] == 0).all()
    # the body's residuals are correlated (or there is nothing to condition on), and the styles
    # (each frame weighed by its style's posterior) differ
    for c in range(C):
        body = cov[c][np.ix_(~root, ~root)]
        d = np.sqrt(np.diag(body))
        corr = body / np.outer(d, d)
        assert np.abs(corr[~np.eye(corr.shape[0], dtype=bool)]).max() > 0.5
    assert np.abs(cov[0] - cov[1]).max() > 1e-3 * np.abs(cov[0]).max()
    assert model.cond is not None and model.cond.shrink == 1.0


def test_the_two_solves_agree(walk):
    model, _, _ = walk
    ct = model.cond
    rng = np.random.default_rng(0)
    F = ct.cov.shape[1]
    for c in range(ct.cov.shape[0]):
        for n_obs in (3, F // 2, F - 3):
            o = np.zeros(F, bool)
            o[rng.choice(F, n_obs, replace=False)] = True
            r = rng.normal(size=n_obs)
            via_q = -np.linalg.solve(ct.prec[c][np.ix_(~o, ~o)], ct.prec[c][np.ix_(~o, o)] @ r)
            via_s = ct.cov[c][np.ix_(~o, o)] @ np.linalg.solve(ct.cov[c][np.ix_(o, o)], r)
            np.testing.assert_allclose(via_q, via_s, rtol=1e-7, atol=1e-9)
            np.testing.assert_allclose(condfill.conditional(ct, c, r, o, ~o), via_s, rtol=1e-7, atol=1e-9)


@pytest.mark.skipif(not fast.enabled(), reason="numba is not installed (or LACUNA_NO_JIT=1)")
def test_compiled_correction_equals_numpy(walk, monkeypatch):
    model, frames, obs = walk
    fa, sa = _run(model, frames, obs, monkeypatch, jit=True)
    fb, sb = _run(model, frames, obs, monkeypatch, jit=False)
    fc, sc = _run(model, frames, obs, monkeypatch, jit=True, batch=True)
    np.testing.assert_allclose(fa, fb, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sa, sb, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fa, fc, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(sa, sc)


def test_correction_moves_only_missing_values_and_shrink_zero_is_eq18(walk, monkeypatch):
    model, frames, obs = walk
    f1, s1 = _run(model, frames, obs, monkeypatch, jit=False)
    plain = model.with_options(cond_shrink=0.0)
    assert plain.cond is None
    f0, s0 = _run(plain, frames, obs, monkeypatch, jit=False)
    np.testing.assert_array_equal(f1[obs], frames[obs])
    np.testing.assert_allclose(s1, s0, rtol=0, atol=1e-9)   # the std stays the filter's
    moved = np.abs(f1 - f0) > 1e-6
    assert not moved[obs].any()
    # it moves the arm's fill and the upper body's under pan2009's pattern
    assert moved[20:70].any() and moved[180:].any()
    # a model without the covariance (a file written before it) fills as eq. (18) alone
    from hlm.model import HLMModel

    old = HLMModel(model.representation, model.params, model.options, model.meta, None)
    assert old.cond is None
    fo, _ = _run(old, frames, obs, monkeypatch, jit=False)
    np.testing.assert_array_equal(fo, f0)


def test_faithful_options_switch_it_off(walk):
    model, _, _ = walk
    assert model.with_options(**FAITHFUL).cond is None


def test_model_file_round_trip_and_old_files(walk, tmp_path, monkeypatch):
    from hlm.model import HLMModel
    from lacuna import modelfile

    model, frames, obs = walk
    p = tmp_path / "m.npz"
    model.save(str(p))
    back = modelfile.load_model(str(p))
    np.testing.assert_array_equal(back.cond_cov, model.cond_cov)
    assert back.options.cond_shrink == 1.0
    fa, _ = _run(model, frames[:120], obs[:120], monkeypatch, jit=False)
    fb, _ = _run(back, frames[:120], obs[:120], monkeypatch, jit=False)
    np.testing.assert_array_equal(fa, fb)
    # a file written before the conditional fill: no cond_cov array, no cond_shrink option
    meta, arrays = modelfile.load_arrays(str(p))
    arrays.pop("cond_cov")
    meta["options"].pop("cond_shrink")
    q = tmp_path / "old.npz"
    modelfile.save_arrays(str(q), meta, arrays)
    old = modelfile.load_model(str(q))
    assert old.cond_cov is None and old.cond is None and old.options.cond_shrink == 0.0
    plain = HLMModel(model.representation, model.params, model.options, model.meta, None)
    fo, _ = _run(old, frames[:120], obs[:120], monkeypatch, jit=False)
    fp, _ = _run(plain, frames[:120], obs[:120], monkeypatch, jit=False)
    np.testing.assert_array_equal(fo, fp)
    # a broken covariance is a clear error, not a silent fill
    bad = dict(arrays, cond_cov=np.triu(model.cond_cov))
    r = tmp_path / "bad.npz"
    modelfile.save_arrays(str(r), meta, bad)
    with pytest.raises(modelfile.ModelFileError, match="cond_cov"):
        modelfile.load_model(str(r))


def test_cli_rejects_a_shrink_outside_0_1(tmp_path):
    import subprocess
    import sys

    out = tmp_path / "m.npz"
    r = subprocess.run([sys.executable, "-m", "lacuna.cli", "train", "hlm", str(tmp_path / "none.amc"), "-o", str(out),
                        "--cond-shrink", "1.5"], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1] == "lacuna: error: --cond-shrink must be in [0, 1] (got 1.5)"
    assert not out.exists()


def test_too_few_training_takes_fit_no_correction(data):
    from mocap.datasets import load_trial

    m = load_trial("35_01")
    model = train_model([m.frames, m.frames[::-1].copy()], m.channels, n_iter=1, restarts=1, styles=1, cond_shrink=0.5)
    assert model.cond is None and model.cond_cov is None and model.options.cond_shrink == 0.0
    assert "2 training takes" in model.meta["training"]["cond_off"]
