"""Joint-position error of a fill, as a studio compares marker positions: forward kinematics
(``mocap.fk``) of the truth and of the fill, and the 3-D distance in cm at every joint whose
position depends on an erased value of that frame (its own filled angle for an ASF bone, a
filled angle anywhere up its chain, or the filled root translation).

    joint_position_error(kin, truth, filled, erased) -> {"mean_cm", "p95_cm", "max_cm", "n"}
"""
from __future__ import annotations

from typing import Any

import numpy as np

from mocap.fk import Kinematics


def joint_errors_cm(kin: Kinematics, truth: np.ndarray, filled: np.ndarray, erased: np.ndarray) -> np.ndarray:
    """(n,) cm: the error of every (frame, joint) moved by an erased value.

    truth, filled : (T, C) in ``kin.channels`` order.  erased : (T, C) bool.  Frames whose truth
    is not all known (a recording's uncaptured values) are left out.
    """
    truth = np.asarray(truth, np.float64)
    filled = np.asarray(filled, np.float64)
    erased = np.asarray(erased, bool)
    ok = np.isfinite(truth).all(1) & np.isfinite(filled).all(1) & erased.any(1)
    if not ok.any():
        return np.zeros(0)
    d = np.linalg.norm(kin.positions(filled[ok]) - kin.positions(truth[ok]), axis=2) * 100.0
    return d[kin.affected(erased[ok])]


def summary(err_cm: np.ndarray) -> dict[str, Any]:
    """mean, 95th percentile and max (cm) and the count of joint-frames."""
    e = np.asarray(err_cm, np.float64)
    if not e.size:
        return {"mean_cm": None, "p95_cm": None, "max_cm": None, "n": 0}
    return {"mean_cm": float(e.mean()), "p95_cm": float(np.percentile(e, 95)), "max_cm": float(e.max()),
            "n": int(e.size)}


def joint_position_error(kin: Kinematics, truth: np.ndarray, filled: np.ndarray, erased: np.ndarray) -> dict[str, Any]:
    return summary(joint_errors_cm(kin, truth, filled, erased))


def positions_motion(kin: Kinematics, frames: np.ndarray, fps: float, source: str = "") -> Any:
    """A Motion of joint positions (metres), channels ``joint.x``, ``.y``, ``.z``, for a CSV."""
    from mocap.motion import Motion

    P = kin.positions(frames)
    names = [f"{j.replace(':', '_')}.{a}" for j in kin.joints for a in "xyz"]
    return Motion(P.reshape(P.shape[0], -1), names, fps, None, source, {"units": "m", "up": kin.up_axis})
