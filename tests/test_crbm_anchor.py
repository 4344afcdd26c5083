"""The faithful ``crbm`` against Taylor's released code (issue 17, part 4): it models the released
code's input (the raw channels of cmu35WalkJog.mat, root as captured, z-scored), fills by the
paper's procedure, and its figures and the released code's saved fills go through one scorer
(``crbm.anchor.cumulative_scaled``, the anchor's crbmfill.m score).
"""
from __future__ import annotations

import numpy as np
import pytest

from crbm import anchor
from crbm.experiment import ANCHOR_METRIC, score_model
from crbm.methods import VARIANTS
from lacuna import registry
from mocap.protocols import get_protocol

pytestmark = [pytest.mark.realdata]


@pytest.fixture(scope="module")
def released(data):
    return anchor.anchor_data()


@pytest.fixture(scope="module")
def tiny(data):
    """``crbm`` as registered, trained for one epoch: the representation and the fill it uses."""
    return registry.get_method("crbm").train(get_protocol("taylor2007").training_set(), hidden=8, epochs=1,
                                             progress=False)


def test_faithful_crbm_models_the_released_codes_input(tiny, released):
    assert VARIANTS["crbm"]["root_mode"] == "raw"
    assert all(VARIANTS[m].get("root_mode", "relative") == "relative" for m in ("crbm-imp", "crbm-ens"))
    rep = tiny.representation
    ts = get_protocol("taylor2007").training_set()
    # the same 56 channels (the 6 constant ones dropped), in the same order, the root's raw
    assert rep.root_mode == "raw" and rep.features == [ts.channels[i] for i in released["keep"]]
    ours = np.vstack([rep.transform(s) for s in ts.sequences])
    theirs = np.vstack(released["sequences"])
    # equal on every channel: no unwrapping either (rhand.rz, whose training values cross
    # +-180 deg, as captured), as train.m's Z = (Y(:,keep) - mu(keep)) ./ sd(keep)
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-9)
    assert not rep.unwrap and tiny.crbm.dtype == "float32"     # mixgaussiancrbm.m: single(...)
    for name, X in released["tests"].items():                 # the test takes likewise
        Zt = (X[:, released["keep"]] - released["mean"][released["keep"]]) / released["std"][released["keep"]]
        np.testing.assert_allclose(rep.transform(X), Zt, rtol=0, atol=1e-9, err_msg=name)


def test_faithful_crbm_fills_by_the_papers_procedure(tiny):
    # K = 30 clamped Gibbs iterations, one chain, sampled hiddens, the final mean-field step from
    # the last iteration's visibles (as crbmfill.m); no per-stream adaptation
    assert (tiny.n_gibbs, tiny.n_chains, tiny.mode, tiny.final_step, tiny.bias_rate) == (30, 1, "gibbs", "last", 0.0)


def test_one_scorer_for_the_released_codes_fills_and_ours(released):
    proto = get_protocol("taylor2007")
    var = released["plain_var"]
    for case in proto.cases():
        cols, st = np.flatnonzero(case.scored), case.info["first_erased"]
        np.testing.assert_array_equal(cols, anchor.GROUPS[case.erased][released["std"][anchor.GROUPS[case.erased]] > 1e-6])
        assert st == case.truth.shape[0] // 2       # crbmfill.m: floor(N / 2) + 1, 1-based
        T = case.truth.shape[0]
        for off in (1.0, 361.0, -359.0):            # angles wrap: all three are one degree off
            fill = case.truth.copy()
            fill[st:, cols] += off
            fill[:st, cols] += 50.0                 # before the gap: not scored
            want = (T - st) * np.mean(1.0 / var[cols])
            assert anchor.cumulative_scaled(fill, case.truth, cols, st, var) == pytest.approx(want, rel=1e-12)


class _Shifted:
    """A 'model' whose offline fill is the truth two degrees off on the erased values."""

    def __init__(self, cases):
        self.cases = cases

    def fill_offline(self, x, observed):
        case = next(c for c in self.cases if c.observed.shape == observed.shape and np.array_equal(c.observed, observed))
        return np.where(observed, x, case.truth + 2.0), None


def test_the_protocols_anchor_metric_is_the_one_scorer(released):
    proto = get_protocol("taylor2007")
    sc = score_model(_Shifted(proto.cases()))
    for case in proto.cases():
        cols, st = np.flatnonzero(case.scored), case.info["first_erased"]
        want = (case.truth.shape[0] - st) * 4.0 * np.mean(1.0 / released["plain_var"][cols])
        assert sc[(case.test, case.erased)][ANCHOR_METRIC] == pytest.approx(want, rel=1e-12)


def test_released_codes_saved_fills_are_scored_with_their_own_indices(released, tmp_path):
    """crbm.anchor.octave_fills reads crbmfill_save.m's FILLS (1-based seq, group, keep, miss, st;
    F over the kept channels in raw units) into the one scorer."""
    import scipy.io

    keep = released["keep"]
    cells = np.empty(2, dtype=object)
    for k, (seq, group, off) in enumerate(((2, 1, 1.0), (1, 2, 3.0))):
        test, g = anchor.TESTS[seq - 1], tuple(anchor.GROUPS)[group - 1]
        X = released["tests"][test]
        cols = anchor.GROUPS[g][released["std"][anchor.GROUPS[g]] > 1e-6]
        miss = np.searchsorted(keep, cols)
        st = X.shape[0] // 2
        F = X[:, keep].copy()
        F[st:, miss] += off
        cells[k] = {"seq": float(seq), "group": float(group), "run": 1.0, "F": F, "keep": (keep + 1).astype(float),
                    "miss": (miss + 1).astype(float), "st": float(st + 1)}
    scipy.io.savemat(tmp_path / "fills.mat", {"FILLS": cells})
    got = anchor.octave_fills(tmp_path / "fills.mat", released)
    assert set(got) == {("35_29", "right-leg"), ("35_18", "upper-body")}
    for (test, g), off in ((("35_29", "right-leg"), 1.0), (("35_18", "upper-body"), 3.0)):
        cols = anchor.GROUPS[g][released["std"][anchor.GROUPS[g]] > 1e-6]
        T = released["tests"][test].shape[0]
        assert got[(test, g)] == [pytest.approx((T - T // 2) * off**2 * np.mean(1.0 / released["plain_var"][cols]), rel=1e-12)]
