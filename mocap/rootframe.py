"""The root's rotation and translation in one canonical frame (y up, R = Rz Ry Rx), whatever the
skeleton: CMU's ASF is already that; CMU's BVH is z up; Mixamo composes ``Zrotation Xrotation
Yrotation``.  ``mocap.representation`` decomposes the canonical orientation into heading, pitch
and roll and the canonical ground plane into side and forward steps, so its root features mean
the same for every skeleton.

A root spec (``mocap.skelmap.Binding.root_spec``) is ``{"rot": [x, y, z rotation channels],
"order": composition order ("zxy": R = Rz Rx Ry), "pos": [x, y, z translation channels], "up"}``.

Canonical coordinates: ``p_c = Q p`` and ``R_c = Q R R_rest^T Q^T`` with Q the rotation that
takes the file's up axis to y (z up: Q = Rx(-90), (x, y, z) -> (x, z, -y); x up: Q = Rz(90))
and R_rest the root's orientation when the performer stands upright (the spec's ``rest``, root
rotation channel values x, y, z in degrees; CMU's BVH has its Hips at ``Xrotation 90`` in its
T-pose, so without it every frame would decompose near pitch 90, where heading is undefined).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from mocap.rootrot import _matrix_to_rxyz as matrix_to_rxyz
from mocap.rootrot import _rxyz_to_matrix as rxyz_to_matrix
from mocap.rootrot import wrap180

_AXES = "xyz"
_Q = {
    "y": np.eye(3),
    "z": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
    "x": np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
}


def _elem(axis: int, a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[..., axis, axis] = 1.0
    R[..., i, i] = c
    R[..., j, j] = c
    R[..., i, j] = -s
    R[..., j, i] = s
    return R


def euler_to_matrix(angles: np.ndarray, order: str) -> np.ndarray:
    """(n, 3) radians in composition order -> (n, 3, 3), R = R_order[0] R_order[1] R_order[2]."""
    R = _elem(_AXES.index(order[0]), angles[..., 0])
    for k in (1, 2):
        R = R @ _elem(_AXES.index(order[k]), angles[..., k])
    return R


def matrix_to_euler(R: np.ndarray, order: str, prev_deg: np.ndarray) -> np.ndarray:
    """Both Tait-Bryan solutions of R = R_i(a) R_j(b) R_k(c) (order "ijk"), in degrees, the one
    nearer ``prev_deg`` (n, 3) chosen.  With s = +1 for a cyclic order (xyz, yzx, zxy), else -1:
    b = asin(s R[i,k]), a = atan2(-s R[j,k], R[k,k]), c = atan2(-s R[i,j], R[i,i]); the other
    solution is (a + 180, 180 - b, c + 180)."""
    i, j, k = (_AXES.index(a) for a in order)
    s = 1.0 if (j - i) % 3 == 1 else -1.0
    b = np.arcsin(np.clip(s * R[..., i, k], -1.0, 1.0))
    a = np.arctan2(-s * R[..., j, k], R[..., k, k])
    c = np.arctan2(-s * R[..., i, j], R[..., i, i])
    s1 = np.rad2deg(np.stack([a, b, c], -1))
    s2 = np.stack([s1[..., 0] + 180.0, 180.0 - s1[..., 1], s1[..., 2] + 180.0], -1)
    d1 = np.abs(wrap180(s1 - prev_deg)).sum(-1)
    d2 = np.abs(wrap180(s2 - prev_deg)).sum(-1)
    return wrap180(np.where((d2 < d1)[..., None], s2, s1))


class RootFrame:
    """Root channels <-> canonical orientation matrices and positions, vectorised over rows."""

    def __init__(self, spec: dict[str, Any] | None) -> None:
        spec = spec or {}
        self.order = str(spec.get("order", "zyx")).lower()
        self.up = str(spec.get("up", "y")).lower()
        if sorted(self.order) != list(_AXES) or self.up not in _Q:
            raise ValueError(f"root spec: order must be a permutation of xyz and up one of x, y, z (got {spec})")
        rest = [float(v) for v in spec.get("rest") or (0.0, 0.0, 0.0)]
        # CMU ASF's own convention: the original algebra, bit for bit
        self.identity = self.order == "zyx" and self.up == "y" and not any(rest)
        self.perm = [_AXES.index(a) for a in self.order]  # composition position -> x, y, z column
        Rrest = euler_to_matrix(np.deg2rad(np.array(rest)[self.perm])[None], self.order)[0]
        self.Q = _Q[self.up]
        self.left = self.Q                      # R_c = left @ R @ right
        self.right = Rrest.T @ self.Q.T

    def matrix(self, rxyz: np.ndarray) -> np.ndarray:
        """(n, 3) rotation channels (x, y, z; radians) -> (n, 3, 3) canonical orientation."""
        if self.identity:
            return rxyz_to_matrix(rxyz[:, 0], rxyz[:, 1], rxyz[:, 2])
        return self.left @ euler_to_matrix(rxyz[:, self.perm], self.order) @ self.right

    def angles(self, Rc: np.ndarray, prev_xyz_deg: np.ndarray) -> np.ndarray:
        """(n, 3, 3) canonical orientation -> (n, 3) rotation channels (x, y, z; degrees) nearest prev."""
        if self.identity:
            return matrix_to_rxyz(Rc, prev_xyz_deg)
        comp = matrix_to_euler(self.left.T @ Rc @ self.right.T, self.order, prev_xyz_deg[:, self.perm])
        out = np.empty_like(comp)
        out[:, self.perm] = comp
        return out

    def to_canonical(self, p: np.ndarray) -> np.ndarray:
        """(n, 3) translation channels (x, y, z) -> canonical (ground x, height y, ground z)."""
        return p if self.identity else p @ self.Q.T

    def from_canonical(self, pc: np.ndarray) -> np.ndarray:
        return pc if self.identity else pc @ self.Q
