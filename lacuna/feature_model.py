"""Models that learn in the feature space of ``mocap.representation`` share this plumbing.

A subclass supplies a *core* that works on normalised features, batched over streams:

    core_init(n) -> dict[str, ndarray]             per-stream state, every array (n, ...)
    core_step(state, z, zobs) -> CoreOut           z: (n, F) features, NaN where missing;
                                                    zobs: (n, F) bool.  Updates state in place.

and this class turns it into the Filler seam: raw frames in, representation encode, core step,
decode, exact pass-through of observed channels, commit.  ``step_batch`` stacks the per-stream
states, runs one vectorised core step and scatters the rows back, so the daemon serves many
performers with one call.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from lacuna.filler import Fill, FillerState, Model, check_frame
from mocap.representation import Representation, ReprState


@dataclass
class CoreOut:
    """z: (n, F) completed normalised features; z_std: (n, F) predictive std (0 where observed);
    extras: per-stream dicts (style posterior, phase, ...)."""

    z: np.ndarray
    z_std: np.ndarray
    extras: list[dict[str, Any]] = field(default_factory=list)


class FeatureModel(Model):
    representation: Representation

    # ---- hooks ----------------------------------------------------------------------------------
    def core_init(self, n: int) -> dict[str, np.ndarray]:
        raise NotImplementedError

    def core_step(self, state: dict[str, np.ndarray], z: np.ndarray, zobs: np.ndarray) -> CoreOut:
        raise NotImplementedError

    # ---- seam -----------------------------------------------------------------------------------
    @property
    def channels(self) -> list[str]:  # type: ignore[override]
        return self.representation.channels

    def stream(self) -> "FeatureStream":
        return FeatureStream(self)

    def _raw_std(self, z_std: np.ndarray) -> np.ndarray:
        """Feature std (normalised units) -> raw channel std (degrees / length units)."""
        rep = self.representation
        return rep.raw_std(z_std * rep._plan()["std"] if rep.normalize else z_std)

    def step_arrays(self, repr_state: ReprState, core_state: dict[str, np.ndarray],
                    frames: np.ndarray, observed: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[dict[str, Any]]]:
        """One vectorised step over n streams.  frames, observed: (n, C).  Returns (completed, std, extras)."""
        z, zobs = repr_state.encode(frames, observed)
        out = self.core_step(core_state, z, zobs)
        completed = repr_state.decode(out.z, frames, observed)
        repr_state.commit(completed)
        std = np.where(observed, 0.0, self._raw_std(out.z_std))
        return completed, std, out.extras

    def step_batch(self, states: Sequence[FillerState], frames: np.ndarray, observed: np.ndarray) -> list[Fill]:
        mine = [s for s in states if isinstance(s, FeatureStream) and s.model is self]
        if len(mine) != len(states):
            return super().step_batch(states, frames, observed)
        frames = np.asarray(frames, dtype=np.float64)
        observed = np.asarray(observed, dtype=bool)
        n = len(mine)
        rs = self.representation.new_state(n)
        for attr in ("prev_u", "prev_raw", "prev_yaw", "started"):
            setattr(rs, attr, np.concatenate([getattr(s.repr_state, attr) for s in mine]))
        cs = {k: np.concatenate([s.core_state[k] for s in mine]) for k in mine[0].core_state}
        done, std, extras = self.step_arrays(rs, cs, np.where(observed, frames, np.nan), observed)
        fills = []
        for i, s in enumerate(mine):
            for attr in ("prev_u", "prev_raw", "prev_yaw", "started"):
                getattr(s.repr_state, attr)[:] = getattr(rs, attr)[i : i + 1]
            for k in cs:
                s.core_state[k][:] = cs[k][i : i + 1]
            fills.append(Fill(done[i], std[i], ~observed[i], extras[i] if extras else {}))
        return fills


class FeatureStream(FillerState):
    """One stream of a FeatureModel: its representation state and its core state (n = 1)."""

    def __init__(self, model: FeatureModel):
        self.model = model
        self.repr_state = model.representation.new_state(1)
        self.core_state = model.core_init(1)

    def step(self, frame: np.ndarray | None, observed: np.ndarray | None = None) -> Fill:
        f, obs = check_frame(frame, observed, self.model.n_channels)
        done, std, extras = self.model.step_arrays(self.repr_state, self.core_state, f[None], obs[None])
        return Fill(done[0], std[0], ~obs, extras[0] if extras else {})
