"""Shared fixtures.  Tests that need the real CMU data take the ``data`` fixture: it skips with a
clear message only when no data directory exists (and .ci/run turns any such skip into a
failure, because CI always has ../shared/data)."""
from __future__ import annotations

import os
import warnings

import numpy as np
import pytest

from mocap.datasets import data_dir


def pytest_report_header(config):
    return [f"lacuna data dir: {data_dir()}", f"LACUNA_TEST_SEED={_seed()}", _swept()]


def _swept() -> str:
    """Daemons left behind by an earlier run's harness that died without stopping them (stopped ones
    never exit on their own, and all of them hold CPU or ports): killed before this run starts."""
    from clients.harness import sweep_orphans

    killed = sweep_orphans()
    return f"orphaned harness daemons killed: {killed}" if killed else "orphaned harness daemons: none"


def _seed() -> int:
    return int(os.environ.get("LACUNA_TEST_SEED", "1234"))


@pytest.fixture
def seed() -> int:
    return _seed()


@pytest.fixture
def rng(seed) -> np.random.Generator:
    return np.random.default_rng(seed)


@pytest.fixture(scope="session")
def data():
    d = data_dir()
    if d is None:
        if os.environ.get("LACUNA_REQUIRE_DATA"):
            pytest.fail("REAL DATA MISSING and LACUNA_REQUIRE_DATA is set (CI must run the real-data tests)")
        pytest.skip("REAL DATA MISSING: no CMU data directory ($LACUNA_DATA or ../shared/data)")
    return d


@pytest.fixture(scope="session")
def small_walk_hlm(data, tmp_path_factory) -> str:
    """The path of a real HLM trained in seconds on three subject-35 walks (35_01, 35_06, 35_07;
    3 EM iterations, 1 restart, 2 styles), trained once a session.  Load a copy of your own
    (``lacuna.modelfile.load_model``): a model's pool holds the streams of whoever steps it."""
    from hlm.methods import train_model
    from mocap.datasets import load_trial

    train = [load_trial(t) for t in ("35_01", "35_06", "35_07")]
    model = train_model([m.frames for m in train], list(train[0].channels), n_iter=3, restarts=1, styles=2)
    path = tmp_path_factory.mktemp("small-walk-hlm") / "hlm.npz"
    model.save(str(path))
    return str(path)


@pytest.fixture(autouse=True)
def _float_warnings():
    with np.errstate(over="raise", invalid="raise", divide="raise"):
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            yield
