"""A take's leading T-pose: CMU's BVH files start with one (frame 0 is the rest pose the
converter added; frame t + 1 is AMC frame t, see tests/test_fk.py), and a model that learns
from it, or a fill scored on it, sees a jump no performer made.

``leading_tpose(frames, channels)`` says whether frame 0 is such a frame: its largest angle
change to frame 1 is more than TPOSE_MIN_DEG and more than TPOSE_RATIO times the 99th
percentile of the take's own frame-to-frame changes (CMU BVH 07_01, 08_02, 09_11: 76, 87, 111
degrees against 12.9, 19.2, 17.2; CMU AMC 07_01: 2.7 against 12.3).
"""
from __future__ import annotations

import sys
from collections.abc import Sequence

import numpy as np

from mocap.motion import Motion
from mocap.representation import is_angle, wrap180

TPOSE_MIN_DEG = 30.0
TPOSE_RATIO = 2.0


def leading_tpose(frames: np.ndarray, channels: Sequence[str]) -> bool:
    """True when frame 0 (of (T, C) frames) is a rest pose jumping to the motion at frame 1."""
    F = np.asarray(frames, dtype=np.float64)
    ang = np.array([is_angle(c) for c in channels])
    if F.shape[0] < 3 or not ang.any():
        return False
    A = F[:, ang]
    with np.errstate(invalid="ignore"):
        step = np.nan_to_num(np.abs(wrap180(np.diff(A, axis=0))), nan=0.0).max(1)
    typical = float(np.percentile(step[1:], 99))
    return bool(step[0] > TPOSE_MIN_DEG and step[0] > TPOSE_RATIO * typical)


def skip_tpose(motion: Motion, quiet: bool = False) -> Motion:
    """The motion without a leading T-pose frame (``meta["tpose_skipped"] = 1``), else itself."""
    if not leading_tpose(motion.frames, motion.channels):
        return motion
    if not quiet:
        print(f"lacuna: {motion.source or 'take'}: frame 0 is a T-pose (rest pose before the motion); skipped",
              file=sys.stderr)
    out = motion.slice(1)
    out.meta["tpose_skipped"] = 1
    return out
