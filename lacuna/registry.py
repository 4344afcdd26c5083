"""Methods register themselves here; `lacuna eval`, replay and the daemon look them up by name.

A method module calls ``register_method(MethodSpec(...))`` at import time and, for saveable
models, ``lacuna.modelfile.register_loader``.  The modules are listed in METHOD_MODULES so that
registration happens without the caller importing them by hand.
"""
from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# Modules that register methods when imported.  Missing ones (a package not built yet) are skipped.
METHOD_MODULES = ["mocap.baselines", "hlm.methods", "crbm.methods", "blend.methods"]


@dataclass
class MethodSpec:
    """How to train and run one method.

    train : (TrainingSet, **options) -> Model.  ``options`` come from the protocol (e.g.
        ``cycle_frames``) and the command line; a method ignores what it does not use.
    fill : (model, frames, observed) -> (filled, std), both (n_frames, n_channels).  None means
        the causal stream (``Model.fill_offline`` default).  Offline methods supply their own.
    causal : False for methods that look at the future (marked in tables and JSON).
    """

    name: str
    train: Callable[..., Any]
    description: str = ""
    fill: Callable[[Any, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
    causal: bool = True
    defaults: dict[str, Any] = field(default_factory=dict)

    def run(self, model: Any, frames: np.ndarray, observed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.fill is not None:
            return self.fill(model, frames, observed)
        return model.fill_offline(frames, observed)


_METHODS: dict[str, MethodSpec] = {}
_loaded = False


def register_method(spec: MethodSpec) -> None:
    _METHODS[spec.name] = spec


def ensure_loaded() -> None:
    global _loaded
    if _loaded:
        return
    _loaded = True
    for mod in METHOD_MODULES:
        try:
            importlib.import_module(mod)
        except ModuleNotFoundError as e:
            if e.name and mod.startswith(e.name):
                continue  # that package is not built yet
            raise


def get_method(name: str) -> MethodSpec:
    ensure_loaded()
    if name not in _METHODS:
        raise KeyError(f"unknown method {name!r} (known: {', '.join(sorted(_METHODS))})")
    return _METHODS[name]


def methods() -> list[str]:
    ensure_loaded()
    return sorted(_METHODS)
