"""Rotation algebra of the root (vectorised over rows), for ``mocap.representation``.

Conventions (CMU ASF, Y up): orientation matrix R = Rz(rz) Ry(ry) Rx(rx) and the heading
decomposition R = Ry(yaw) Rx(pitch) Rz(roll).
"""
from __future__ import annotations

import numpy as np


def wrap180(x: np.ndarray) -> np.ndarray:
    """Wrap angles in degrees into [-180, 180)."""
    return (np.asarray(x) + 180.0) % 360.0 - 180.0


def _rxyz_to_matrix(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """R = Rz(c) Ry(b) Rx(a), angles in radians, shape (n,) -> (n, 3, 3)."""
    ca, sa, cb, sb, cc, sc = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    R = np.empty(a.shape + (3, 3))
    R[..., 0, 0] = cc * cb
    R[..., 0, 1] = cc * sb * sa - sc * ca
    R[..., 0, 2] = cc * sb * ca + sc * sa
    R[..., 1, 0] = sc * cb
    R[..., 1, 1] = sc * sb * sa + cc * ca
    R[..., 1, 2] = sc * sb * ca - cc * sa
    R[..., 2, 0] = -sb
    R[..., 2, 1] = cb * sa
    R[..., 2, 2] = cb * ca
    return R


def _matrix_to_ypr(R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """R = Ry(yaw) Rx(pitch) Rz(roll): row 1 is (cp sr, cp cr, -sp); column 2 is (sy cp, ., cy cp)."""
    pitch = np.arcsin(np.clip(-R[..., 1, 2], -1.0, 1.0))
    roll = np.arctan2(R[..., 1, 0], R[..., 1, 1])
    yaw = np.arctan2(R[..., 0, 2], R[..., 2, 2])
    return yaw, pitch, roll


def _ypr_to_matrix(y: np.ndarray, p: np.ndarray, r: np.ndarray) -> np.ndarray:
    cy, sy, cp, sp, cr, sr = np.cos(y), np.sin(y), np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    R = np.empty(y.shape + (3, 3))
    R[..., 0, 0] = cy * cr + sy * sp * sr
    R[..., 0, 1] = -cy * sr + sy * sp * cr
    R[..., 0, 2] = sy * cp
    R[..., 1, 0] = cp * sr
    R[..., 1, 1] = cp * cr
    R[..., 1, 2] = -sp
    R[..., 2, 0] = -sy * cr + cy * sp * sr
    R[..., 2, 1] = sy * sr + cy * sp * cr
    R[..., 2, 2] = cy * cp
    return R


def _matrix_to_rxyz(R: np.ndarray, prev: np.ndarray) -> np.ndarray:
    """Both Euler solutions of R = Rz Ry Rx; pick the one nearer ``prev`` (n, 3) degrees."""
    b1 = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    a1 = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    c1 = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    s1 = np.rad2deg(np.stack([a1, b1, c1], -1))
    s2 = np.stack([s1[..., 0] + 180.0, 180.0 - s1[..., 1], s1[..., 2] + 180.0], -1)
    d1 = np.abs(wrap180(s1 - prev)).sum(-1)
    d2 = np.abs(wrap180(s2 - prev)).sum(-1)
    return wrap180(np.where((d2 < d1)[..., None], s2, s1))
