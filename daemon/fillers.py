"""Fillers the daemon needs besides trained models: the pass-through floor.

``PassThroughModel`` returns every frame as it came and fills nothing: the daemon with it
measures the transport's own latency floor (``lacuna bench --floor``), and a studio can use it
to relay a stream unchanged.  Hold-last-value under overload is done by the session itself
(daemon/session.py), so it works whatever model serves the stream.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lacuna.filler import Fill, FillerState, Model, check_frame


class PassThroughModel(Model):
    """Marks nothing filled; missing values stay NaN with std 0."""

    method = "passthrough"

    def __init__(self, channels: list[str] | None = None):
        # no channel list = "any": a stream's handshake (or its first frame's width) decides,
        # which is what a latency-floor measurement wants
        self.channels = list(channels or [])

    @property
    def any_channels(self) -> bool:
        return not self.channels

    def stream(self) -> PassThroughState:
        return PassThroughState(self)

    def info(self) -> dict:
        return {"method": self.method, "channels": len(self.channels) or "any", "causal": True}

    def step_batch(self, states: Sequence[FillerState], frames: np.ndarray, observed: np.ndarray) -> list[Fill]:
        frames = np.asarray(frames, dtype=np.float64)
        observed = np.asarray(observed, dtype=bool)
        out = np.where(observed, frames, np.nan)
        z = np.zeros(out.shape[1])
        none = np.zeros(out.shape[1], bool)
        return [Fill(out[i], z, none) for i in range(len(states))]


class PassThroughState(FillerState):
    def __init__(self, model: PassThroughModel):
        self.model = model

    def step(self, frame: np.ndarray | None, observed: np.ndarray | None = None) -> Fill:
        if frame is None:  # a predicted frame: nothing to pass through (width unknown for "any")
            C = self.model.n_channels
            return Fill(np.full(C, np.nan), np.zeros(C), np.zeros(C, bool))
        C = self.model.n_channels or np.asarray(frame).shape[0]
        f, obs = check_frame(frame, observed, C)
        return Fill(np.where(obs, f, np.nan), np.zeros(C), np.zeros(C, bool))
