"""CRBM model files: ``lacuna.modelfile`` npz arrays + JSON meta, never pickle.

Arrays: ``W, A, B, c, b`` (first level) and ``l2_W, l2_A, l2_B, l2_c, l2_b`` (second level,
optional); an ensemble (``crbm-ens``) stores member i as ``m{i}_W, m{i}_A, ...``.  Meta: channels, representation, hyperparameters of each level, fill settings,
training data names / seconds / date / epochs / last reconstruction error.

The models write their own files (``CRBMModel.save``); this module reads them back.
"""
from __future__ import annotations

import os
from typing import Any

import numpy as np

from crbm.ensemble import CRBMEnsemble
from crbm.filler import CRBMModel
from crbm.model import CRBM
from lacuna.modelfile import ModelFileError, load_arrays
from mocap.representation import Representation

METHODS = ("crbm", "crbm-mf", "crbm-2level", "crbm-imp", "crbm-ens")


def load_model_arrays(path: str, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> CRBMModel:
    """The registered loader: rebuilds the model, ModelFileError naming the file on bad content."""
    try:
        rep = Representation.from_dict(meta["representation"])
        hyper = meta["hyperparameters"]
        fill = meta.get("fill", {})
        knobs = dict(n_gibbs=fill.get("n_gibbs", 30), n_chains=fill.get("n_chains", 1),
                     mode=fill.get("mode", "gibbs"), init_noise=fill.get("init_noise", 0.01),
                     bias_rate=fill.get("bias_rate", 0.0),
                     # a file saved before final_step existed filled with the "input" order
                     final_step=fill.get("final_step", "input"), meta={"training": meta.get("training", {})})
        if "members" in hyper:
            members = [CRBM.from_arrays(h, arrays, f"m{i}_") for i, h in enumerate(hyper["members"])]
            model: CRBMModel = CRBMEnsemble(rep, members, **knobs)
        else:
            l1 = CRBM.from_arrays(hyper["level1"], arrays)
            l2 = CRBM.from_arrays(hyper["level2"], arrays, "l2_") if "level2" in hyper else None
            model = CRBMModel(rep, l1, l2, **knobs)
    except KeyError as e:
        raise ModelFileError(f"{path}: crbm model lacks {e.args[0]!r}") from None
    except ValueError as e:
        raise ModelFileError(f"{path}: crbm model is malformed ({e})") from None
    if list(meta["channels"]) != list(model.channels):
        raise ModelFileError(f"{path}: metadata channels do not match the representation's channels")
    if meta.get("method") in METHODS:
        model.method = meta["method"]
    return model


def load(path: str | os.PathLike) -> CRBMModel:
    path = os.fspath(path)
    meta, arrays = load_arrays(path)
    if meta.get("method") not in METHODS:
        raise ModelFileError(f"{path}: method {meta.get('method')!r} is not a CRBM model")
    return load_model_arrays(path, meta, arrays)
