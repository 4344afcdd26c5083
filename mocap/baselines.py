"""The simple baselines, behind the same Filler seam as the models.

hold       hold-last-value, causal: each missing channel keeps its last observed value.
nn         nearest neighbour (Taylor et al. 2006; Pan & Torresani 2009): for each frame, the
           training frame closest in Euclidean distance over the observed channels (raw
           degrees), whose values fill the missing channels.  Causal, per frame.
scaled-nn  the same with every channel scaled to unit training variance ("normalized angle
           space" in Taylor et al.).
interp     linear interpolation across each gap from the last observed value to the next one
           (unwrapped angles); an offline reference: it needs the future.  A gap that runs to
           the end of the take is held.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from lacuna import modelfile
from lacuna.filler import Fill, FillerState, Model, check_frame
from lacuna.registry import MethodSpec, register_method
from mocap.representation import circular_mean_deg, is_angle, wrap180


def _channel_stats(frames: np.ndarray, channels: list[str]) -> tuple[np.ndarray, np.ndarray]:
    ang = np.array([is_angle(c) for c in channels])
    mean = np.where(ang, circular_mean_deg(frames), frames.mean(0))
    dev = np.where(ang[None], wrap180(frames - mean), frames - mean)
    return mean, np.sqrt(np.mean(dev**2, 0))


class _Saveable(Model):
    def _meta(self) -> dict[str, Any]:
        return {"method": self.method, "channels": self.channels}


# ---- hold ---------------------------------------------------------------------------------------
class HoldModel(_Saveable):
    """Holds the last observed value; before any observation, the training mean.  The std of a
    held value is the channel's training std (an honest 'could be anywhere in the range')."""

    method = "hold"

    def __init__(self, channels: list[str], mean: np.ndarray, std: np.ndarray):
        self.channels = list(channels)
        self.mean_ = np.asarray(mean, dtype=np.float64)
        self.std_ = np.asarray(std, dtype=np.float64)

    @classmethod
    def fit(cls, sequences: list[np.ndarray], channels: list[str]) -> HoldModel:
        mean, std = _channel_stats(np.vstack(sequences), channels)
        return cls(channels, mean, std)

    def stream(self) -> HoldState:
        return HoldState(self)

    def step_batch(self, states, frames, observed):
        mine = all(isinstance(s, HoldState) for s in states)
        if not mine or not len(states):
            return super().step_batch(states, frames, observed)
        frames = np.asarray(frames, dtype=np.float64)
        observed = np.asarray(observed, dtype=bool)
        last = np.stack([s.last for s in states])
        out = np.where(observed, frames, last)
        std = np.where(observed, 0.0, self.std_[None])
        fills = []
        for i, s in enumerate(states):
            s.last = out[i].copy()
            fills.append(Fill(out[i], std[i], ~observed[i]))
        return fills

    def save(self, path: str) -> None:
        modelfile.save_arrays(path, self._meta(), {"mean": self.mean_, "std": self.std_})

    @classmethod
    def load(cls, path: str, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> HoldModel:
        C = len(meta["channels"])
        return cls(meta["channels"], modelfile.require(path, arrays, "mean", (C,)),
                   modelfile.require(path, arrays, "std", (C,)))


class HoldState(FillerState):
    def __init__(self, model: HoldModel):
        self.model = model
        self.last = model.mean_.copy()

    def step(self, frame, observed=None) -> Fill:
        m = self.model
        f, obs = check_frame(frame, observed, m.n_channels)
        out = np.where(obs, f, self.last)
        self.last = out.copy()
        return Fill(out, np.where(obs, 0.0, m.std_), ~obs)


# ---- nearest neighbour ----------------------------------------------------------------------------
class NearestNeighbourModel(_Saveable):
    """Per-frame nearest neighbour over the observed channels.

    train_ : (n_train, n_channels) raw training frames.  scale_ : (n_channels,) divisor applied
    before distances (ones for ``nn``, training std for ``scaled-nn``).
    """

    def __init__(self, channels: list[str], train: np.ndarray, scale: np.ndarray, method: str = "nn"):
        self.channels = list(channels)
        self.train_ = np.asarray(train, dtype=np.float64)
        self.scale_ = np.where(np.asarray(scale) > 1e-9, scale, 1.0)
        self.method = method  # type: ignore[misc]
        self._z = self.train_ / self.scale_

    @classmethod
    def fit(cls, sequences: list[np.ndarray], channels: list[str], scaled: bool = False) -> NearestNeighbourModel:
        train = np.vstack(sequences)
        scale = _channel_stats(train, channels)[1] if scaled else np.ones(train.shape[1])
        return cls(channels, train, scale, "scaled-nn" if scaled else "nn")

    def nearest(self, frames: np.ndarray, observed: np.ndarray) -> np.ndarray:
        """Indices (n,) of the nearest training frame for each row, over that row's observed channels."""
        frames = np.atleast_2d(frames)
        observed = np.atleast_2d(observed)
        out = np.zeros(frames.shape[0], int)
        # rows sharing a mask share one matrix product: ||a-b||^2 = |a|^2 - 2ab + |b|^2 (|a|^2 is constant per row)
        keys, inv = np.unique(observed, axis=0, return_inverse=True)
        for k, mask in enumerate(keys):
            rows = np.flatnonzero(inv.ravel() == k)
            if not mask.any():
                out[rows] = 0
                continue
            zt = self._z[:, mask]
            q = frames[np.ix_(rows, np.flatnonzero(mask))] / self.scale_[mask]
            d = (zt**2).sum(1)[None, :] - 2.0 * q @ zt.T
            out[rows] = d.argmin(1)
        return out

    def fill(self, frames: np.ndarray, observed: np.ndarray) -> np.ndarray:
        idx = self.nearest(np.where(observed, frames, 0.0), observed)
        return np.where(observed, frames, self.train_[idx])

    def stream(self) -> NNState:
        return NNState(self)

    def step_batch(self, states, frames, observed):
        frames = np.asarray(frames, dtype=np.float64)
        observed = np.asarray(observed, dtype=bool)
        out = self.fill(frames, observed)
        return [Fill(out[i], np.zeros(self.n_channels), ~observed[i]) for i in range(len(states))]

    def fill_offline(self, frames, observed):
        return self.fill(np.asarray(frames, dtype=np.float64), np.asarray(observed, bool)), np.zeros(np.shape(frames))

    def save(self, path: str) -> None:
        modelfile.save_arrays(path, self._meta(), {"train": self.train_, "scale": self.scale_})

    @classmethod
    def load(cls, path: str, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> NearestNeighbourModel:
        C = len(meta["channels"])
        return cls(meta["channels"], modelfile.require(path, arrays, "train", (None, C)),
                   modelfile.require(path, arrays, "scale", (C,)), meta["method"])


class NNState(FillerState):
    def __init__(self, model: NearestNeighbourModel):
        self.model = model

    def step(self, frame, observed=None) -> Fill:
        m = self.model
        f, obs = check_frame(frame, observed, m.n_channels)
        out = m.fill(f[None], obs[None])[0]
        return Fill(out, np.zeros(m.n_channels), ~obs)


# ---- linear interpolation (offline) ---------------------------------------------------------------
class InterpModel(HoldModel):
    """Offline reference: linear interpolation across gaps (needs the frame after the gap)."""

    method = "interp"
    causal = False

    def fill_offline(self, frames, observed):
        frames = np.asarray(frames, dtype=np.float64)
        observed = np.asarray(observed, bool)
        out = frames.copy()
        t = np.arange(frames.shape[0])
        for j, c in enumerate(self.channels):
            o = observed[:, j]
            if o.all():
                continue
            if not o.any():
                out[:, j] = self.mean_[j]
                continue
            v = frames[o, j]
            if is_angle(c):
                v = np.rad2deg(np.unwrap(np.deg2rad(v)))
            filled = np.interp(t, t[o], v)  # holds the end values beyond the first/last observation
            out[~o, j] = wrap180(filled[~o]) if is_angle(c) else filled[~o]
        return out, np.where(observed, 0.0, self.std_[None])


def _train_hold(ts, **_):
    return HoldModel.fit(ts.sequences, ts.channels)


def _train_interp(ts, **_):
    m = HoldModel.fit(ts.sequences, ts.channels)
    return InterpModel(m.channels, m.mean_, m.std_)


register_method(MethodSpec("hold", _train_hold, "hold-last-value (causal)"))
register_method(MethodSpec("nn", lambda ts, **_: NearestNeighbourModel.fit(ts.sequences, ts.channels, False),
                           "nearest neighbour on raw degrees (per frame)"))
register_method(MethodSpec("scaled-nn", lambda ts, **_: NearestNeighbourModel.fit(ts.sequences, ts.channels, True),
                           "nearest neighbour on unit-variance channels (per frame)"))
register_method(MethodSpec("interp", _train_interp, "linear interpolation across the gap (offline: needs the future)",
                           causal=False))
modelfile.register_loader("hold", HoldModel.load)
modelfile.register_loader("interp", lambda p, m, a: InterpModel(*_hold_args(p, m, a)))
modelfile.register_loader("nn", NearestNeighbourModel.load)
modelfile.register_loader("scaled-nn", NearestNeighbourModel.load)


def _hold_args(path, meta, arrays):
    h = HoldModel.load(path, meta, arrays)
    return h.channels, h.mean_, h.std_
