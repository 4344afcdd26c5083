"""``lacuna train crbm`` / ``lacuna generate crbm`` / ``lacuna eval --method crbm`` as real
processes on real files (issue 4, deliverables 1, 3 and 5)."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from mocap.asf import read_amc


def lacuna(*args: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lacuna.cli", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


@pytest.fixture(scope="module")
def small_model(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("crbm") / "m.npz"
    walk, run = data / "cmu" / "35" / "35_01.amc", data / "cmu" / "35" / "35_17.amc"
    r = lacuna("train", "crbm", "--hidden", "20", "--epochs", "15", str(walk), str(run), "-o", str(out))
    assert r.returncode == 0, r.stderr
    assert "crbm epoch 1: reconstruction error" in r.stderr and "wrote" in r.stdout
    return out


def test_issue4_train_writes_a_loadable_model(small_model):
    from lacuna.modelfile import load_model

    m = load_model(str(small_model))
    assert m.method == "crbm" and m.crbm.n_hidden == 20 and m.crbm.n_epochs_done_ == 15
    assert m.meta["training"]["data"] == ["35_01", "35_17"] and m.meta["training"]["fps"] == 30.0
    # the faithful crbm models the released code's input: the root channels as captured
    assert m.representation.root_mode == "raw" and m.representation.root is None


def test_issue4_generate_writes_amc_with_the_seed_skeleton(small_model, data, tmp_path):
    out = tmp_path / "gen.amc"
    seed = data / "cmu" / "35" / "35_17.amc"
    r = lacuna("generate", "crbm", str(small_model), "--seed-frames", str(seed), "--frames", "30", "-o", str(out),
               "--asf", str(data / "cmu" / "35" / "35.asf"))
    assert r.returncode == 0, r.stderr
    m = read_amc(str(out), str(data / "cmu" / "35" / "35.asf"))
    # 4 seed + 30 generated frames at 30 Hz, written at the seed's 120 Hz
    assert m.n_frames == (4 + 30 - 1) * 4 + 1
    assert np.all(np.isfinite(m.frames))
    src = read_amc(str(seed))
    np.testing.assert_allclose(m.frames[0], src.frames[0], atol=1e-9)


def test_issue4_eval_scores_a_crbm_model_file(small_model):
    r = lacuna("eval", "--protocol", "taylor2007", "--method", "crbm", "--model", str(small_model), "-q")
    assert r.returncode == 0, r.stderr
    # one block per erasure pattern, a column per test take: the 4 cases
    assert r.stdout.count("cumulative_scaled_error") == 2
    assert "erased: right-leg" in r.stdout and "erased: upper-body" in r.stdout
    for line in (ln for ln in r.stdout.splitlines() if ln.startswith("cumulative_scaled_error")):
        assert len([v for v in line.split()[1:] if float(v) > 0]) == 2


def test_bad_input_gives_one_line_errors(small_model, tmp_path):
    r = lacuna("train", "crbm", str(tmp_path / "nope.amc"), "-o", str(tmp_path / "x.npz"))
    assert r.returncode == 2 and "nope.amc: no such file" in r.stderr and "Traceback" not in r.stderr
    r = lacuna("train", "crbm", "-o", str(tmp_path / "x.npz"))
    assert r.returncode == 2 and "neither" in r.stderr
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a model")
    r = lacuna("generate", "crbm", str(bad), "--seed-frames", "x.amc", "--frames", "3", "-o", str(tmp_path / "o.amc"))
    assert r.returncode == 2 and "bad.npz" in r.stderr and "Traceback" not in r.stderr
    r = lacuna("train", "crbm", "--protocol", "taylor2007", "--hidden", "0", "--epochs", "1", "-o", str(tmp_path / "x.npz"))
    assert r.returncode == 2 and "n_hidden" in r.stderr
