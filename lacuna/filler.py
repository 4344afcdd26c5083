"""The one seam: every method that fills frames answers this interface.

A *model* is an immutable object (trained, or loaded from a file).  ``model.stream()`` gives a
fresh per-stream state whose ``step(frame, observed)`` is causal: it sees frame t and the past
only, and returns a :class:`Fill`.  ``model.step_batch(states, frames, observed)`` steps many
streams at once (the daemon's hot path); the default loops, models override it to vectorise.
Offline methods (smoothing over a whole recording) implement ``fill_offline`` and set
``causal = False``.

Frames are always in the model's *raw* channel space: plain joint angles in degrees (and root
translation in ASF length units), one float per entry of ``model.channels``.  Representation
(unwrapping, root motion, normalisation) happens inside the model (see ``mocap.representation``);
callers never see it.

Arrays
------
frame : (n_channels,) float64, values of unobserved channels are ignored (may be NaN)
observed : (n_channels,) bool, True where the value was measured this frame
"""
from __future__ import annotations

import abc
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np


class FillerError(ValueError):
    """A frame or a model that a filler cannot use (wrong width, non-finite observed value)."""


@dataclass
class Fill:
    """One filled frame.

    Attributes
    ----------
    frame : (n_channels,) completed frame; observed channels are returned exactly as given.
    std : (n_channels,) predictive standard deviation of each value; 0 where observed.
    filled : (n_channels,) bool, True where the value was filled in (i.e. not observed).
    extras : model extras, e.g. ``{"style": (n_styles,) posterior, "phase": float in [0, 1)}``.
    degraded : True when the filler took a cheaper path than asked (daemon under load).
    """

    frame: np.ndarray
    std: np.ndarray
    filled: np.ndarray
    extras: dict[str, Any] = field(default_factory=dict)
    degraded: bool = False


@dataclass
class BlockFill:
    """n filled frames as arrays (:meth:`Model.step_block`): what n :class:`Fill` objects hold,
    a row each, without an object per stream.

    frame : (n, C) float64; std : (n, C); filled : (n, C) bool.
    style : (n, K) style posteriors, or a list of n (each None or a posterior), or None: no
        stream has one.
    phase : (n,) floats (NaN: none), or a list of n (each None or a float), or None: none.
    degraded : list of n bools (``Fill.degraded``), or None: none degraded.
    """

    frame: np.ndarray
    std: np.ndarray
    filled: np.ndarray
    style: np.ndarray | list[Any] | None = None
    phase: np.ndarray | list[Any] | None = None
    degraded: list[bool] | None = None

    @classmethod
    def of(cls, fills: Sequence[Fill], C: int) -> BlockFill:
        """The n Fills (each of C channels) as one block; raises :class:`FillsDoNotStack` (which
        keeps them) where they are not n rows of C."""
        n = len(fills)
        try:
            frame = np.array([f.frame for f in fills], dtype=np.float64)
            std = np.array([f.std for f in fills], dtype=np.float64)
            filled = np.array([f.filled for f in fills], dtype=bool)
        except (ValueError, TypeError) as e:
            raise FillsDoNotStack(list(fills), str(e)) from e
        if not (frame.shape == std.shape == filled.shape == (n, C)):
            raise FillsDoNotStack(list(fills), f"fills do not stack to ({n}, {C})")
        exs = [f.extras or _NONE for f in fills]
        return cls(frame, std, filled, [ex.get("style") for ex in exs], [ex.get("phase") for ex in exs],
                   [f.degraded for f in fills])


class FillsDoNotStack(ValueError):
    """Fills that are not n rows of C channels (:meth:`BlockFill.of`); ``fills`` keeps them."""

    def __init__(self, fills: list[Fill], why: str):
        super().__init__(why)
        self.fills = fills


_NONE: dict[str, Any] = {}


def check_frame(frame: Any, observed: Any, n_channels: int) -> tuple[np.ndarray, np.ndarray]:
    """Validate one frame and its mask; returns float64 frame and bool mask copies.

    ``frame=None`` is a frame that never arrived: all NaN, nothing observed.  Raises FillerError
    naming what arrived when the width is wrong or an observed value is not finite (NaN in an
    *unobserved* slot is the normal way to say "missing").
    """
    if frame is None:
        return np.full(n_channels, np.nan), np.zeros(n_channels, bool)
    f = np.asarray(frame, dtype=np.float64)
    if f.ndim != 1 or f.shape[0] != n_channels:
        raise FillerError(f"frame must have {n_channels} channels (got shape {f.shape})")
    if observed is None:
        obs = np.isfinite(f)
    else:
        obs = np.asarray(observed, dtype=bool)
        if obs.shape != (n_channels,):
            raise FillerError(f"observed mask must have {n_channels} entries (got shape {obs.shape})")
        bad = obs & ~np.isfinite(f)
        if bad.any():
            idx = np.flatnonzero(bad)[:5].tolist()
            raise FillerError(f"observed values must be finite (got NaN/inf at channels {idx})")
    return f.copy(), obs.copy()


class FillerState(abc.ABC):
    """Per-stream state.  O(1) memory and time per frame for causal models."""

    @abc.abstractmethod
    def step(self, frame: np.ndarray | None, observed: np.ndarray | None = None) -> Fill:
        """Consume frame t (``None`` = the frame never arrived: a pure prediction step)."""

    def predict(self) -> Fill:
        """A frame that never arrived: everything is missing."""
        return self.step(None, None)


class Model(abc.ABC):
    """A trained filler.  Subclasses set ``method`` and ``channels`` and implement ``stream``."""

    method: ClassVar[str] = "?"
    causal: ClassVar[bool] = True
    # fills nothing (frames go back as they came): a scheduler neither plans nor warms it up
    passthrough: ClassVar[bool] = False
    channels: list[str]

    def quality_levels(self) -> list[int | None]:
        """The degradation levels ``step_batch`` takes, full quality first (cheaper after it).
        ``[None]``: none, every step is at full quality."""
        return [None]

    @property
    def n_channels(self) -> int:
        return len(self.channels)

    @abc.abstractmethod
    def stream(self) -> FillerState:
        """A fresh per-stream state."""

    def step_batch(
        self,
        states: Sequence[FillerState],
        frames: np.ndarray,
        observed: np.ndarray,
        level: int | None = None,
    ) -> list[Fill]:
        """Step many streams at once.  frames, observed: (n_streams, n_channels).  ``level``:
        one of :meth:`quality_levels` for this step only (None: full quality); the model is not
        changed by it."""
        return [s.step(f, o) for s, f, o in zip(states, frames, observed)]

    def step_block(self, states: Sequence[FillerState], frames: np.ndarray, observed: np.ndarray,
                   level: int | None = None) -> BlockFill:
        """:meth:`step_batch` with the fills as (n, C) arrays (the daemon's bundle path).  This
        default stacks ``step_batch``'s Fills (:meth:`BlockFill.of`: raises
        :class:`FillsDoNotStack` where they do not stack); a model that can write its fills
        straight into arrays overrides it with the same results."""
        fills = self.step_batch(states, frames, observed) if level is None else \
            self.step_batch(states, frames, observed, level=level)
        return BlockFill.of(fills, np.shape(observed)[1])

    def fill_offline(self, frames: np.ndarray, observed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fill a whole recording.  frames, observed: (n_frames, n_channels).

        Returns (filled frames, std), both (n_frames, n_channels).  The default runs the causal
        stream over the recording; non-causal models override this.
        """
        st = self.stream()
        out = np.empty_like(frames, dtype=np.float64)
        std = np.zeros_like(out)
        for t in range(frames.shape[0]):
            fill = st.step(frames[t], observed[t])
            out[t] = fill.frame
            std[t] = fill.std
        return out, std

    def info(self) -> dict[str, Any]:
        """Short description for `lacuna status` / `list models`."""
        return {"method": self.method, "channels": len(self.channels), "causal": self.causal}

    # Persistence: models that can be saved implement these (see lacuna.modelfile).
    def save(self, path: str) -> None:  # pragma: no cover - overridden
        raise NotImplementedError(f"{type(self).__name__} cannot be saved")
