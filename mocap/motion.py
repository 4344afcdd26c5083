"""The in-memory form of a take: frames of named channels at a frame rate."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class Motion:
    """A recording.

    Attributes
    ----------
    frames : (n_frames, n_channels) float64; angles in degrees, translations in file units.
    channels : channel names, ``bone.dof`` (``root.tx``, ``lfemur.rx``, ``Hips.rz``).
    fps : frames per second.
    skeleton : the format's skeleton (``mocap.asf.Skeleton`` or ``mocap.bvh.Hierarchy``), kept so
        a writer can reproduce the file; None for CSV.
    source : the file it came from, for messages.
    """

    frames: np.ndarray
    channels: list[str]
    fps: float = 120.0
    skeleton: Any = None
    source: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.frames = np.asarray(self.frames, dtype=np.float64)
        if self.frames.ndim != 2 or self.frames.shape[1] != len(self.channels):
            raise ValueError(
                f"frames must be (n_frames, {len(self.channels)}) for {len(self.channels)} channels "
                f"(got shape {self.frames.shape})"
            )

    @property
    def n_frames(self) -> int:
        return self.frames.shape[0]

    def index(self, names: Sequence[str]) -> np.ndarray:
        """Column indices of the named channels; KeyError naming the first missing one."""
        pos = {c: i for i, c in enumerate(self.channels)}
        out = []
        for n in names:
            if n not in pos:
                raise KeyError(f"channel {n!r} not in {self.source or 'motion'}")
            out.append(pos[n])
        return np.asarray(out, dtype=int)

    def select(self, names: Sequence[str]) -> Motion:
        """A copy with only (and in the order of) the named channels."""
        return Motion(self.frames[:, self.index(names)].copy(), list(names), self.fps, None, self.source, dict(self.meta))

    def slice(self, start: int, stop: int | None = None, step: int = 1) -> Motion:
        return Motion(self.frames[start:stop:step].copy(), list(self.channels), self.fps / step, self.skeleton, self.source, dict(self.meta))
