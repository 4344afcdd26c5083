"""The small real ``default`` the default-model tests train (tests/test_default_hlm.py,
test_default_long_gate.py, test_default_long_ll.py): its takes and HLM settings, and a model's experts
mixed anew with other settings in its metadata."""
from __future__ import annotations

from typing import Any

from blend.withhlm import WithHLMModel, shipped, train_model
from lacuna import jit
from mocap import protocols

TRAIN_TAKES = ["07_02", "07_09", "35_01", "35_06", "35_07", "35_08", "walking_13", "walking_14",
               "basketball_1", "soccer_1", "basketball_signal_1"]
SMALL_HLM = {"restarts": 1, "n_iter": 6, "screen_iters": None, "cycle_frames": 140}


def train_small() -> WithHLMModel:
    """``default`` trained on TRAIN_TAKES with the HLM trained small (seconds, not minutes)."""
    return train_model(protocols.named_training_set(TRAIN_TAKES), **SMALL_HLM)


def remix(model: WithHLMModel, meta: dict[str, Any], compiled: bool = True) -> WithHLMModel:
    """``model``'s experts mixed anew by the shipped weights, with ``meta`` (e.g. {"long_gate": [...]})."""
    W, S, _ = shipped()
    m = WithHLMModel(model.default, model.hlm, W, S, meta, tau=model.tau, cal=model.calib, smooth=model.smooth,
                     rate_ref=model.rate_ref, band_q=model.band_q, band_gate=model.band_gate)
    m.compiled = compiled and jit.enabled()
    return m
