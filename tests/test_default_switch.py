"""``default`` is now the mixed filler (blend.withhlm); the stacked blend stays reachable as
``default-blend``, and model files of the old kind "default" (the stacked blend's) still load and
fill as they did.  Real takes: trained on two TRAIN takes, filled on a TEST take."""
from __future__ import annotations

import numpy as np
import pytest

from blend.fit import occlusion
from blend.methods import _train, _train_with_hlm
from blend.model import DefaultModel
from blend.train import train_model as train_blend
from blend.withhlm import WithHLMModel
from lacuna import modelfile, registry
from lacuna.cli import main as cli_main
from mocap import splits

pytestmark = pytest.mark.realdata

TAKES = ("07_02", "walking_13")


def test_default_names_the_mixed_filler_and_default_blend_the_stacked_blend():
    assert {"default", "default-blend", "default-hlm"} <= set(registry.methods())
    mixed, blend = registry.get_method("default"), registry.get_method("default-blend")
    assert mixed.causal and blend.causal
    # the registry's trainers: default (and its earlier name default-hlm) train blend.withhlm's model
    assert mixed.train is _train_with_hlm and registry.get_method("default-hlm").train is _train_with_hlm
    assert blend.train is _train


def test_a_model_file_of_the_old_kind_default_loads_and_fills_as_before(data, tmp_path, capsys):
    """`lacuna train default-blend` writes what `lacuna train default` wrote before the switch (kind
    "default"): it loads as the stacked blend and fills a TEST take exactly as the blend trained
    in-process does; `lacuna eval --model` scores it whatever --method names it."""
    files = [str(splits.take_path(t)) for t in TAKES]
    out = tmp_path / "old.npz"
    assert cli_main(["train", "default-blend", *files, "-o", str(out), "-q"]) == 0
    meta, _ = modelfile.load_arrays(str(out))
    assert meta["method"] == "default"          # the old kind, unchanged
    loaded = modelfile.load_model(str(out))
    assert isinstance(loaded, DefaultModel)
    seqs = [splits.load_take(t).frames for t in TAKES]
    ref = train_blend(seqs, splits.load_take(TAKES[0]).channels, [f"{t}.amc" for t in TAKES], fps=120.0)
    truth = splits.load_take("35_30").frames[:300]
    obs, _ = occlusion("35_30", 300, loaded.channels, 120.0, seed=101)
    given = np.where(obs, truth, np.nan)
    a, sa = loaded.fill_offline(given, obs)
    b, sb = ref.fill_offline(given, obs)
    assert (~obs).sum() > 500
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sa, sb, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(a[obs], truth[obs])
    rc = cli_main(["eval", "--protocol", "gaps", "--split", "test", "--method", "default", "--model", str(out),
                   "--test", str(splits.take_path("35_30")), "-q"])
    assert rc == 0 and "rms_deg" in capsys.readouterr().out


def test_train_default_writes_the_mixed_filler(data, tmp_path):
    """`lacuna train default` (tiny HLM settings through the registry's options) gives a model of
    kind "default-hlm" whose experts are the stacked blend and the HLM."""
    from mocap import protocols

    ms = [splits.load_take(t) for t in TAKES]
    ts = protocols.TrainingSet([m.frames for m in ms], ms[0].channels, 120.0, list(TAKES), ["walk", "walk"])
    m = registry.get_method("default").train(ts, restarts=1, n_iter=3, screen_iters=None, cycle_frames=140)
    p = tmp_path / "mixed.npz"
    m.save(str(p))
    assert modelfile.load_arrays(str(p))[0]["method"] == "default-hlm"
    back = modelfile.load_model(str(p))
    assert isinstance(back.default, DefaultModel) and back.hlm.method == "hlm"
    assert isinstance(m, WithHLMModel) and isinstance(back, WithHLMModel)
