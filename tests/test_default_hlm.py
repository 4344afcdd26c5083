"""``default-hlm`` (blend/withhlm.py): default and the HLM side by side, on real takes.

The experts are trained small (a few TRAIN takes, the HLM with one restart and few EM steps) so the
file stays within the suite's budget; the stacking weights are the shipped ones (fitted on
VALIDATION by bench/default_hlm_tune.py).  Scored on TEST takes.
"""
from __future__ import annotations

import numpy as np
import pytest

from blend.withhlm import ROOT_POS, WithHLMModel, train_model
from lacuna import jit, modelfile
from lacuna.cli import main as cli_main
from mocap import protocols, splits
from mocap.representation import is_angle
from mocap.rootrot import wrap180 as wrap

pytestmark = pytest.mark.realdata

TRAIN_TAKES = ["07_02", "07_09", "35_01", "35_06", "35_07", "35_08", "walking_13", "walking_14",
               "basketball_1", "soccer_1", "basketball_signal_1"]
SMALL_HLM = {"restarts": 1, "n_iter": 6, "screen_iters": None, "cycle_frames": 140}


@pytest.fixture(scope="module")
def model(data):
    names = TRAIN_TAKES
    ms = [splits.load_take(t) for t in names]
    ts = protocols.TrainingSet([m.frames for m in ms], ms[0].channels, 120.0, names,
                               [splits.ACTIVITY[t] for t in names])
    return train_model(ts, **SMALL_HLM)


def _pan2009(truth: np.ndarray, channels: list[str]) -> np.ndarray:
    legs = np.array([c.split(".")[0] in ("lfemur", "ltibia", "lfoot", "ltoes", "rfemur", "rtibia", "rfoot", "rtoes")
                     for c in channels])
    obs = np.ones(truth.shape, bool)
    obs[truth.shape[0] // 2:, ~legs] = False
    return obs


def _mse(truth, fill, obs, channels) -> float:
    ang = np.array([is_angle(c) for c in channels])
    e = wrap(fill - truth)[~obs & ang[None]]
    return float(np.mean(e ** 2))


def test_beats_default_on_a_test_walk_with_pan2009s_pattern(model):
    """TEST walk 35_30 (a subject-35 walk nobody trains or tunes on), root and upper body erased from
    half way: the blend's erased angles beat ``default``'s own, and the root position is default's."""
    truth = splits.load_take("35_30").frames
    ch = model.channels
    obs = _pan2009(truth, ch)
    given = np.where(obs, truth, np.nan)
    fill, std = model.fill_offline(given, obs)
    dfill, _ = model.default.fill_offline(given, obs)
    hfill, _ = model.hlm.fill_offline(given, obs)
    assert _mse(truth, fill, obs, ch) < 0.8 * _mse(truth, dfill, obs, ch)
    np.testing.assert_array_equal(fill[obs], truth[obs])        # observed values come back exactly
    assert (std[~obs] > 0).all() and (std[obs] == 0).all()
    pos = model.group == ROOT_POS
    np.testing.assert_allclose(fill[:, pos], dfill[:, pos])     # root translation: never the HLM's
    assert not np.allclose(fill[:, pos], hfill[:, pos])


def test_no_worse_than_default_on_a_test_take_that_is_not_locomotion(model):
    """TEST take basketball_signal_5 (referee signals), the gaps protocol's bursts: the shadow check
    sees that the HLM does not predict this body (q > 1) and the blend stays within 3% of
    ``default`` (q > 1.1 yields entirely; 3% is for the first second, before the first shadow
    windows, when q is still its prior 1 and the validation-fitted cells give the HLM a share;
    measured: 1.00x default, q 5.4)."""
    c = [c for c in protocols.Gaps(seed=0, split="test").cases() if c.test == "basketball_signal_5"][0]
    T = 900
    truth, obs = c.truth[:T], c.observed[:T]
    given = np.where(obs, truth, np.nan)
    st = model.stream()
    fill = np.empty(truth.shape)
    for t in range(T):
        fill[t] = st.step(given[t], obs[t]).frame
    dfill, _ = model.default.fill_offline(given, obs)
    assert st.m is model and np.exp(st.logq) > 1.0
    assert _mse(truth, fill, obs, c.channels) <= 1.03 * _mse(truth, dfill, obs, c.channels)


def test_model_file_round_trip_and_batch_equals_streams(model, tmp_path):
    truth = splits.load_take("walking_27").frames[:400]
    obs = _pan2009(truth, model.channels)
    obs[:100, :] = True
    p = str(tmp_path / "dh.npz")
    model.save(p)
    back = modelfile.load_model(p)
    assert isinstance(back, WithHLMModel) and back.tau == model.tau
    np.testing.assert_array_equal(back.W, model.W)
    a, sa = model.fill_offline(np.where(obs, truth, np.nan), obs)
    b, sb = back.fill_offline(np.where(obs, truth, np.nan), obs)
    np.testing.assert_allclose(a, b, atol=1e-9)
    np.testing.assert_allclose(sa, sb, atol=1e-9)
    # two streams through step_batch (the daemon's path) give what each stream gives alone
    obs2 = obs.copy()
    obs2[150:250, :20] = False
    states = [back.stream(), back.stream()]
    F = np.stack([truth, truth], 1)
    O = np.stack([obs, obs2], 1)
    out = np.stack([[f.frame for f in back.step_batch(states, F[t], O[t])] for t in range(len(truth))])
    np.testing.assert_allclose(out[:, 0], b, atol=1e-9)
    c, _ = back.fill_offline(np.where(obs2, truth, np.nan), obs2)
    np.testing.assert_allclose(out[:, 1], c, atol=1e-9)


def test_truncated_model_file_is_a_clear_error(model, tmp_path, capsys):
    p = tmp_path / "dh.npz"
    model.save(str(p))
    cut = tmp_path / "cut.npz"
    cut.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    with pytest.raises(modelfile.ModelFileError, match="truncated or corrupt"):
        modelfile.load_model(str(cut))
    rc = cli_main(["eval", "--protocol", "pan2009", "--split", "test", "--method", "default-hlm", "--model", str(cut), "-q"])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("lacuna: error:") and "cut.npz" in err and len(err.strip().splitlines()) == 1
    # a file whose experts' metadata is missing names what is wrong
    meta, arrays = modelfile.load_arrays(str(p))
    del meta["experts"]
    bad = tmp_path / "bad.npz"
    modelfile.save_arrays(str(bad), meta, arrays)
    with pytest.raises(modelfile.ModelFileError, match="two experts"):
        modelfile.load_model(str(bad))


def test_train_without_a_locomotion_file_is_a_clear_error(data, tmp_path, capsys):
    files = [str(splits.take_path(t)) for t in ("basketball_1", "soccer_1")]
    rc = cli_main(["train", "default-hlm", *files, "-o", str(tmp_path / "dh.npz"), "-q"])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("lacuna: error:") and "locomotion" in err
    assert not (tmp_path / "dh.npz").exists()


@pytest.mark.skipif(not jit.enabled(), reason="numba cannot run in this process: only the numpy mixing serves")
def test_compiled_mixing_equals_the_numpy_mixing(model):
    """TEST take 35_30 with the gaps protocol's bursts (seed 0): one stream mixed by the compiled
    kernel (blend/withhlm_fast.py), one by the numpy reference, frame by frame; fills and stds agree
    to 1e-9 through real gaps and through shadow windows (their twin and q included)."""
    c = [c for c in protocols.Gaps(seed=0, split="test").cases() if c.test == "35_30"][0]
    T = len(c.truth)
    a, b = model.stream(), model.stream()
    windows = gaps = 0
    try:
        for t in range(T):
            model.compiled = True
            fa = a.step(c.truth[t], c.observed[t])
            model.compiled = False
            fb = b.step(c.truth[t], c.observed[t])
            np.testing.assert_allclose(fa.frame, fb.frame, rtol=0, atol=1e-9)
            np.testing.assert_allclose(fa.std, fb.std, rtol=0, atol=1e-9)
            windows += a.sh >= 0
            gaps += fa.filled.any()
    finally:
        model.compiled = jit.enabled()
    assert windows > 60 and gaps > 60            # both paths were exercised
    assert a.logq != 0.0 and abs(a.logq - b.logq) < 1e-9 and (a.k == b.k).all()
