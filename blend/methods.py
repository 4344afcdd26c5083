"""Registers ``default`` (the stacked blend and the HLM mixed online: blend.withhlm),
``default-blend`` (the stacked blend alone: blend.model) and ``default-hlm`` (default's earlier
name) with ``lacuna.registry``, and their model-file loaders.  Model files keep their kind: "default"
is the stacked blend's (files written before the switch load and fill as they did), "default-hlm"
the mixed filler's."""
from __future__ import annotations

from typing import Any

from blend.model import DefaultModel
from lacuna.modelfile import register_loader
from lacuna.registry import MethodSpec, register_method


def _train(training_set: Any, **options: Any) -> DefaultModel:
    from blend.train import train_model

    return train_model(training_set.sequences, training_set.channels, list(getattr(training_set, "names", []) or []),
                       fps=options.get("fps") or getattr(training_set, "fps", None),
                       skeleton=getattr(training_set, "skeleton", None))


register_method(MethodSpec("default-blend", _train,
                           "hold, damped velocity and a regression on the observed channels, anchored at the last "
                           "value and stacked by weights chosen on validation (blend; default's first expert)",
                           None, True))
register_loader("default", DefaultModel.load)   # the stacked blend's files (kind "default", before and after the switch)


def _train_with_hlm(training_set: Any, **options: Any):
    from blend.withhlm import train_model

    return train_model(training_set, **options)


def _load_with_hlm(path: str, meta: dict[str, Any], arrays: dict[str, Any]):
    from blend.withhlm import WithHLMModel

    return WithHLMModel.load(path, meta, arrays)


register_method(MethodSpec("default", _train_with_hlm,
                           "the recommended causal filler: default-blend and the HLM's online filter (trained on the "
                           "locomotion takes) side by side, weighed per joint group by how well the HLM predicts what "
                           "is still observed (blend.withhlm)", None, True))
register_method(MethodSpec("default-hlm", _train_with_hlm, "the same as default (its name before it became default)",
                           None, True))
register_loader("default-hlm", _load_with_hlm)
