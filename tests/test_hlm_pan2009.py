"""The paper's experiment (section 4.3) on the real data, as CI: pan2009 protocol, HLM against the
nearest neighbour computed here.  Targets (issue 3): offline <= 0.39 x nn (the paper's 9.3 / 23.9),
online causal <= 0.5 x nn; subject-35 walks and runs fall into separate styles."""
import numpy as np
import pytest

from hlm.offline import purity
from lacuna import registry
from mocap.protocols import get_protocol

pytestmark = [pytest.mark.slow, pytest.mark.realdata]


@pytest.fixture(scope="module")
def trained(data):
    proto = get_protocol("pan2009")
    ts = proto.training_set()
    spec = registry.get_method("hlm")
    model = spec.train(ts, **{**proto.options, **spec.defaults})
    return proto, ts, model


def _mse(proto, case, filled):
    return next(r["value"] for r in proto.score(case, filled) if r["metric"] == "mse_deg2")


def test_pan2009_fill_beats_nearest_neighbour_by_the_papers_margin(trained):
    proto, ts, model = trained
    case = proto.cases()[0]
    given = np.where(case.observed, case.truth, np.nan)
    nn = registry.get_method("nn")
    nn_mse = _mse(proto, case, nn.run(nn.train(ts), given, case.observed.copy())[0])
    assert 10.0 < nn_mse < 25.0          # the baseline this protocol is known for (about 15.8)
    off = _mse(proto, case, registry.get_method("hlm-offline").run(model, given, case.observed.copy())[0])
    on_filled, on_std = registry.get_method("hlm").run(model, given, case.observed.copy())
    on = _mse(proto, case, on_filled)
    print(f"pan2009: nn {nn_mse:.2f}  hlm-offline {off:.2f} ({off / nn_mse:.3f})  hlm online {on:.2f} ({on / nn_mse:.3f})")
    assert off <= 0.39 * nn_mse
    assert on <= 0.5 * nn_mse
    # observed channels come back exactly; filled ones carry a positive std, except the channels
    # that are constant in all training data (clavicles, fingers), which are restored exactly
    np.testing.assert_array_equal(on_filled[case.observed], case.truth[case.observed])
    varying = np.asarray(model.representation.keep)
    assert (on_std[~case.observed & (case.scored & varying)[None, :]] > 0).all()
    assert (on_std[:, ~varying] == 0).all()


def test_pan2009_training_styles_separate_walks_from_runs(trained):
    proto, ts, model = trained
    psi = np.array(model.meta["training"]["psi"])
    s35 = np.array([n.startswith("35_") for n in ts.names])
    p = purity(psi.argmax(1)[s35], np.array(ts.labels)[s35])
    print(f"subject-35 walk/run purity {p:.3f}; bounds {model.meta['training']['bounds'][-3:]}")
    assert p >= 0.9
    b = model.meta["training"]["bounds"]
    assert np.all(np.diff(b) >= -1e-8 * np.abs(b[1:]))
