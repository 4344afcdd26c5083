"""The section-5 fill-in experiment on the real taylor2007 split, and section 4.1's walking and
running from one model (issue 4, targets).

Trains the improved CRBM ensemble (``crbm-ens``: three ``crbm-imp`` CRBMs of 1300 epochs from
training seeds 0, 1000, 2000, filling together from one shared history, about 80-115 s) and the
faithful one (CD-1 as the released code runs it, K = 30 Gibbs, one chain) at 1000 epochs, and scores both with
the protocol's cumulative scaled error against the nearest neighbours computed here.

With per-stream bias adaptation (``bias_rate`` 0.02, ``crbm.filler``), measured on this
machine: seed 0 (this test, 5 repeats) 0.514 leg / 0.428 body, both inside the issue's targets
(<= 0.53 / <= 0.43 x the better nearest neighbour on 35_29); seeds 0 / 1 / 2 (3 repeats) 0.516 /
0.531 / 0.526 leg and 0.427 / 0.419 / 0.376 body, mean 0.524 / 0.407 (docs/BENCHMARKS.md,
## CRBM).  The margins are a few thousandths, and another BLAS or numpy build changes the
1300-epoch training trajectories as a change of seed does (seeds move the leg by +-0.01), so the
test asserts the ratios with 0.02 of headroom (ASSERTED) and prints the measured values.
"""
from __future__ import annotations

import time

import numpy as np
import pytest

from crbm.experiment import METRIC, baseline_scores, ratios, score_model, table
from crbm.generate import generate
from lacuna import registry
from mocap.protocols import get_protocol
from mocap.representation import resample

pytestmark = [pytest.mark.slow, pytest.mark.realdata]

WALK = ("35_29", "right-leg"), ("35_29", "upper-body")
TARGET = {"right-leg": 0.53, "upper-body": 0.43}      # the paper's 11.7/22.2 and 8.8/20.5
ASSERTED = {"right-leg": 0.55, "upper-body": 0.45}    # the targets + 0.02: see the module docstring
REPEATS = 5                                            # stochastic fills averaged, as the paper did


@pytest.fixture(scope="module")
def proto(data):
    return get_protocol("taylor2007")


@pytest.fixture(scope="module")
def base(proto):
    return baseline_scores()


def _train(proto, method, **kw):
    t0 = time.perf_counter()
    model = registry.get_method(method).train(proto.training_set(), **{**proto.options, **kw})
    return model, time.perf_counter() - t0


@pytest.fixture(scope="module")
def improved(proto):
    return _train(proto, "crbm-ens")


@pytest.fixture(scope="module")
def faithful(proto):
    # half the schedule to save test time; it only has to beat nearest neighbour here.  Trained
    # as the released code trains, on its raw-root input (since 2026-12-01); the full 2000-epoch
    # runs give 35_29 8.12 / 13.41, ratios 0.62 / 0.57, mean of training seeds 0-4
    # (bench/notebook/crbm2.md compares it with the released code itself; too slow for this test)
    return _train(proto, "crbm", epochs=1000)


def test_issue4_taylor2007_improved_crbm_meets_the_paper_ratios(improved, base):
    model, secs = improved
    sc = score_model(model, repeats=REPEATS, seed=0)
    r = ratios(sc, base)
    print(f"\ncrbm-ens trained in {secs:.1f} s\n" + table({**base, "crbm-ens": sc}))
    print({f"{t} {e}": round(x, 3) for (t, e), x in r.items()})
    for key in WALK:
        assert r[key] <= ASSERTED[key[1]], (f"{key}: {sc[key][METRIC]:.2f} is x{r[key]:.2f} of the better nn "
                                            f"(issue target x{TARGET[key[1]]})")
    # the jog is reported, and must at least beat the nearest neighbours
    assert r[("35_18", "right-leg")] < 1.0 and r[("35_18", "upper-body")] < 1.0


def test_issue4_taylor2007_faithful_crbm_beats_nearest_neighbour(faithful, base):
    model, secs = faithful
    sc = score_model(model, repeats=REPEATS, seed=0)
    r = ratios(sc, base)
    print(f"\ncrbm (faithful) trained in {secs:.1f} s\n" + table({**base, "crbm": sc}))
    print({f"{t} {e}": round(x, 3) for (t, e), x in r.items()})
    for key in sc:
        assert r[key] < 1.0, f"{key}: faithful CRBM {sc[key][METRIC]:.2f} is not better than nearest neighbour"


def _period(x: np.ndarray) -> int:
    """Dominant period (frames) of a 1-D signal by its autocorrelation's first peak past lag 8."""
    x = x - x.mean()
    ac = np.correlate(x, x, "full")[len(x) - 1 :]
    ac = ac / ac[0]
    lags = np.arange(8, len(x) // 2)
    return int(lags[np.argmax(ac[lags])])


def test_issue4_walks_and_runs_from_one_model(improved, data):
    """Section 4.1: seeded with walking frames it walks, with running frames it runs.  One CRBM
    (the ensemble's first member, a ``crbm-imp`` model): generation follows one sample path."""
    from crbm.filler import CRBMModel
    from mocap.asf import read_amc

    ens, _ = improved
    model = CRBMModel(ens.representation, ens.members[0], n_chains=1)
    col = model.channels.index("lfemur.rx")
    periods = {}
    for kind, trial in (("walk", "35_01"), ("run", "35_17")):
        m = read_amc(str(data / "cmu" / "35" / f"{trial}.amc"))
        frames = resample(m.frames[:, m.index(model.channels)], m.fps, 30.0, model.channels)
        out = generate(model, frames[:4], 150, seed=1)
        gen = out[4 + 30 :, col]     # skip the first second
        assert np.all(np.isfinite(out))
        # the motion keeps going: no collapse to a still pose
        assert gen.std() > 0.4 * frames[:, col].std(), f"{kind}: generated hip swing died out"
        periods[kind] = (_period(gen), _period(frames[:, col]))
    print(f"\ngait periods (generated, seed trial) in frames at 30 Hz: {periods}")
    for kind, (g, s) in periods.items():
        assert abs(g - s) <= 0.25 * s, f"{kind}: generated period {g} frames, the trial's {s}"
    assert periods["run"][0] < periods["walk"][0]
