"""HLM model files: save/load round trip through lacuna.modelfile, and clear errors for bad files;
`lacuna train hlm` on real AMC takes as a real process."""
import subprocess
import sys

import numpy as np
import pytest

from hlm.methods import train_model
from hlm.model import HLMModel
from hlm.synthetic import random_cycles, sample
from lacuna.modelfile import ModelFileError, load_arrays, load_model, save_arrays

F = 5
CH = [f"j{i}.tx" for i in range(F)]


@pytest.fixture(scope="module")
def model():
    rng = np.random.default_rng(5)
    seqs, _ = sample(random_cycles(2, 30, F, rng), np.full((2, F), 4.0), [80] * 6, rng, labels=np.array([0, 1] * 3))
    return train_model(seqs, CH, ["a", "b", "c", "d", "e", "f"], styles=2, cycle_frames=15, restarts=1, n_iter=4,
                       kappa=0.2, lag=7), seqs


def test_round_trip_gives_the_same_filler(model, tmp_path):
    m, seqs = model
    path = str(tmp_path / "m.npz")
    m.save(path)
    m2 = load_model(path)
    assert isinstance(m2, HLMModel)
    assert m2.channels == CH and m2.options == m.options
    for k in ("mu", "var", "lam", "tau", "d", "zbar"):
        np.testing.assert_array_equal(getattr(m2.params, k), getattr(m.params, k))
    assert m2.meta["training"]["data"] == ["a", "b", "c", "d", "e", "f"]
    assert m2.meta["hyperparameters"]["n_states"] == 30
    x = seqs[0]
    obs = np.ones(x.shape, bool)
    obs[40:, :2] = False
    a, b = m.fill_offline(np.where(obs, x, np.nan), obs), m2.fill_offline(np.where(obs, x, np.nan), obs)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def _rewrite(path, out, meta_fn=None, arr_fn=None):
    meta, arrays = load_arrays(path)
    if meta_fn:
        meta_fn(meta)
    if arr_fn:
        arr_fn(arrays)
    save_arrays(out, meta, arrays)


def test_bad_files_are_refused_with_the_cause(model, tmp_path):
    m, _ = model
    good = str(tmp_path / "good.npz")
    m.save(good)
    bad = str(tmp_path / "bad.npz")
    _rewrite(good, bad, arr_fn=lambda a: a.update(lam=a["lam"][:, :3]))
    with pytest.raises(ModelFileError, match="'lam' has shape"):
        load_model(bad)
    _rewrite(good, bad, arr_fn=lambda a: a.update(var=-a["var"]))
    with pytest.raises(ModelFileError, match="positive"):
        load_model(bad)
    _rewrite(good, bad, arr_fn=lambda a: a.update(tau=a["tau"] * 2))
    with pytest.raises(ModelFileError, match="probability"):
        load_model(bad)
    _rewrite(good, bad, arr_fn=lambda a: a.pop("mu"))
    with pytest.raises(ModelFileError, match="missing array 'mu'"):
        load_model(bad)
    _rewrite(good, bad, meta_fn=lambda me: me.update(channels=me["channels"][:-1]))
    with pytest.raises(ModelFileError, match="channel"):
        load_model(bad)
    with open(good, "rb") as fh:
        data = fh.read()
    with open(bad, "wb") as fh:
        fh.write(data[: len(data) // 2])
    with pytest.raises(ModelFileError, match="truncated or corrupt"):
        load_model(bad)


def test_inference_options_are_checked(model):
    m, _ = model
    with pytest.raises(ValueError, match="kappa"):
        m.with_options(kappa=-1.0)
    with pytest.raises(ValueError, match="adapt_rate"):
        m.with_options(adapt_rate=1.5)
    with pytest.raises(ValueError, match="style_switch"):
        m.with_options(style_switch=1.0)


def test_cli_trains_on_real_takes(data, tmp_path):
    out = tmp_path / "hlm.npz"
    files = [str(data / "cmu" / "35" / "35_01.amc"), str(data / "cmu" / "35" / "35_17.amc")]
    r = subprocess.run([sys.executable, "-m", "lacuna.cli", "train", "hlm", "--styles", "2", "--cycle-frames", "50",
                        "--iterations", "3", "--restarts", "2", "--style-switch", "0.001", *files, "-o", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if "iteration" in ln and "bound" in ln]
    assert len(lines) >= 3                                  # a progress line per EM iteration
    m = load_model(str(out))
    assert m.params.n_styles == 2 and m.params.n_states == 100
    assert m.meta["training"]["data"] == ["35_01.amc", "35_17.amc"]
    assert m.options.style_switch == 0.001 and m.tables.style_switch == 0.001   # stored, and used
    # and clear one-line errors
    r = subprocess.run([sys.executable, "-m", "lacuna.cli", "train", "hlm", str(tmp_path / "none.amc"), "-o", str(out)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "none.amc: no such file" in r.stderr and "Traceback" not in r.stderr
