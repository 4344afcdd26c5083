"""Forward kinematics: joint positions in metres from the angles of an ASF/AMC or BVH motion.

    kin = Kinematics.from_motion(motion)        # motion from mocap.io.read_motion
    P = kin.positions(motion.frames)            # (T, J, 3) metres, in the file's world axes
    p = kin.position(motion.frames[0])          # (J, 3)
    kin.joints, kin.parents, kin.segments()     # names, parent index (-1 root), (parent, child)

Conventions (column vectors, ``R @ v``):

* BVH (Meredith & Maddock 2001): a joint's local rotation is the product of its rotation
  channels in the order the file declares them (``Zrotation Xrotation Yrotation`` ->
  ``Rz @ Rx @ Ry``); ``R_j = R_parent @ L_j``; ``p_j = p_parent + R_parent @ (offset_j + t_j)``
  with ``t_j`` the joint's position channels (the root's translation).  End Sites are joints
  (named ``Parent_End``, as ``mocap.bvh`` names them).
* ASF/AMC (Acclaim; CMU's documentation): a bone's motion rotation ``M`` applies its dofs in the
  order listed (``dof rx ry rz`` -> ``M = Rz @ Ry @ Rx``), ``C`` is its ``axis`` rotation in its
  axis order (``axis 0 0 20 XYZ`` -> ``C = Rz(20) @ Ry(0) @ Rx(0)``);
  ``R_b = R_parent @ C @ M @ C^-1`` and the bone's end is ``p_b = p_parent + R_b @ (length *
  direction)``.  The root is ``p = position + (tx, ty, tz)``, ``R = C_root @ M_root @ C_root^-1``
  with the root's ``order`` and ``axis``.  Joints are ``root`` then every bone's end point.

Length units: ASF files say theirs (``:units length 0.45`` means one unit is 1/0.45 inch,
0.0254 / 0.45 = 0.05644 m, CMU's documentation).  BVH files do not; pass ``length_unit``
(metres per file unit), else the skeleton map's (``mocap/skeletons/*.toml``), else the unit among
mm, cm, inch, CMU's 1/0.45 inch and m that makes the rest skeleton nearest 1.7 m tall.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from mocap.motion import Motion

INCH_M = 0.0254
# candidate BVH length units (metres per unit) for the height guess
BVH_UNITS = {"mm": 0.001, "cm": 0.01, "inch": INCH_M, "cmu": INCH_M / 0.45, "m": 1.0}
TYPICAL_HEIGHT_M = 1.7
_AXES = "xyz"


def _elementary(axis: int, rad: np.ndarray, out: np.ndarray) -> None:
    """Fill out (..., 3, 3) with the rotation by ``rad`` (...) about axis 0, 1 or 2."""
    c, s = np.cos(rad), np.sin(rad)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    out[...] = 0.0
    out[..., axis, axis] = 1.0
    out[..., i, i] = c
    out[..., j, j] = c
    out[..., i, j] = -s
    out[..., j, i] = s


def euler_matrix(angles_deg: Sequence[float], order: str) -> np.ndarray:
    """``R = R_order[0](a0) @ R_order[1](a1) @ R_order[2](a2)``, e.g. order "zyx" (3, 3)."""
    R = np.eye(3)
    E = np.empty((3, 3))
    for a, ax in zip(angles_deg, order.lower()):
        _elementary(_AXES.index(ax), np.float64(math.radians(a)), E)
        R = R @ E
    return R


def axis_matrix(xyz_deg: Sequence[float], order: str) -> np.ndarray:
    """ASF ``axis ax ay az ORDER``: the angles are per axis (x, y, z) and applied in ORDER, so
    "XYZ" gives ``Rz(az) @ Ry(ay) @ Rx(ax)`` (3, 3)."""
    by_axis = dict(zip(_AXES, xyz_deg))
    rev = order.lower()[::-1]
    return euler_matrix([by_axis[a] for a in rev], rev)


class Kinematics:
    """A skeleton ready for forward kinematics over frames in a fixed channel order.

    Attributes
    ----------
    joints : joint names in FK order (every parent before its children).
    parents : (J,) parent index per joint, -1 for a root.
    channels : the channel order ``positions`` expects (the motion's).
    length_unit : metres per file length unit.
    up_axis : "x", "y" or "z", the file's vertical axis (ASF: "y"; BVH: the skeleton map's or guessed).
    depends : (J, C) bool, True where joint j's position depends on channel c.
    """

    def __init__(self, joints: list[str], parents: list[int], channels: list[str], offsets: np.ndarray,
                 rot: list[list[tuple[int, int]]], trans: list[list[tuple[int, int]]],
                 pre: np.ndarray, own_rotation_moves: bool, length_unit: float, up_axis: str = "y",
                 kind: str = "") -> None:
        self.joints = list(joints)
        self.parents = [int(p) for p in parents]
        self.channels = list(channels)
        self.length_unit = float(length_unit)
        self.up_axis = up_axis
        self.kind = kind
        J = len(joints)
        if any(p >= i for i, p in enumerate(self.parents)):
            raise ValueError("joints must be in FK order (each parent before its children)")
        self._off = np.asarray(offsets, dtype=np.float64).reshape(J, 3)
        self._rot = rot      # per joint: [(column or -1, axis)] in multiplication order
        self._trans = trans  # per joint: [(column, axis)]
        self._pre = np.asarray(pre, dtype=np.float64).reshape(J, 3, 3)  # C (identity for BVH)
        self._post = np.transpose(self._pre, (0, 2, 1))                # C^-1
        self._own = own_rotation_moves  # ASF: a bone's rotation moves its own end point
        self._cols = [c for r in rot for c, _ in r if c >= 0]
        self._axes = [a for r in rot for c, a in r if c >= 0]
        self._slot = []  # per joint: slice into the stacked elementary rotations
        k = 0
        for r in rot:
            n = sum(1 for c, _ in r if c >= 0)
            self._slot.append(slice(k, k + n))
            k += n
        self._has_pre = [not np.allclose(self._pre[j], np.eye(3)) for j in range(J)]
        dep = np.zeros((J, len(channels)), bool)
        for j in range(J):
            p = self.parents[j]
            if p >= 0:
                dep[j] |= dep[p]
                if not self._own:  # BVH: the parent's rotation moves this joint
                    dep[j, [c for c, _ in rot[p] if c >= 0]] = True
            if self._own:
                dep[j, [c for c, _ in rot[j] if c >= 0]] = True
            dep[j, [c for c, _ in trans[j]]] = True
        self.depends = dep
        self._fast: tuple | None = None  # mocap.fastfk tables, built on the first compiled call

    # ---- construction ------------------------------------------------------------------------
    @classmethod
    def from_motion(cls, motion: Motion, length_unit: float | None = None, up_axis: str | None = None,
                    skeleton: Any = None) -> Kinematics:
        """FK for ``motion.frames`` (its channels, its skeleton).  ValueError for a CSV motion.
        ``skeleton``: the skeleton map (name, file or map) whose length unit and up axis a BVH
        file takes when not given (default: recognised from the bone names)."""
        return cls.from_skeleton(motion.skeleton, motion.channels, length_unit, up_axis,
                                 source=motion.source, frames=motion.frames, skeleton_map=skeleton)

    @classmethod
    def from_skeleton(cls, skeleton: Any, channels: Sequence[str] | None = None, length_unit: float | None = None,
                      up_axis: str | None = None, source: str = "", frames: np.ndarray | None = None,
                      skeleton_map: Any = None) -> Kinematics:
        """FK for an ``mocap.asf.Skeleton`` or ``mocap.bvh.Hierarchy`` over ``channels`` (default:
        the skeleton's own).  Channels the skeleton has but ``channels`` lacks are taken as 0."""
        from mocap.asf import Skeleton
        from mocap.bvh import Hierarchy

        if isinstance(skeleton, Skeleton):
            return _from_asf(skeleton, list(channels or skeleton.channels), length_unit, up_axis)
        if isinstance(skeleton, Hierarchy):
            ch = list(channels or skeleton.channels)
            if length_unit is None or up_axis is None:
                from mocap import skelmap

                try:
                    m = skelmap.resolve(skeleton_map, ch, source)
                except skelmap.SkeletonError:
                    if skeleton_map is not None:
                        raise
                    m = None  # no map knows these bones: guess the unit and the up axis
                if m is not None and m.format == "bvh":
                    length_unit = length_unit if length_unit is not None else m.length_unit
                    up_axis = up_axis or m.up
            return _from_bvh(skeleton, ch, length_unit, up_axis, frames)
        raise ValueError(f"{source or 'this motion'} has no skeleton (a CSV file?): forward kinematics needs "
                         "an ASF/AMC or BVH skeleton (pass --asf for a CSV of ASF channels)")

    # ---- evaluation --------------------------------------------------------------------------
    def positions(self, frames: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """(T, C) frames (degrees; file length units) -> (T, J, 3) joint positions in metres."""
        F = np.asarray(frames, dtype=np.float64)
        if F.ndim != 2 or F.shape[1] != len(self.channels):
            raise ValueError(f"frames must be (n_frames, {len(self.channels)}) (got shape {F.shape})")
        T, J = F.shape[0], len(self.joints)
        E = np.empty((T, len(self._cols), 3, 3))
        for k, (c, a) in enumerate(zip(self._cols, self._axes)):
            _elementary(a, np.deg2rad(F[:, c]), E[:, k])
        R = np.empty((T, J, 3, 3))
        P = np.empty((T, J, 3)) if out is None else out
        for j in range(J):
            L = None
            for k in range(self._slot[j].start, self._slot[j].stop):
                L = E[:, k] if L is None else L @ E[:, k]
            if self._has_pre[j] and L is not None:
                L = self._pre[j] @ L @ self._post[j]
            p = self.parents[j]
            off = np.broadcast_to(self._off[j], (T, 3)).copy()
            for c, a in self._trans[j]:
                off[:, a] += F[:, c]
            if p < 0:
                R[:, j] = np.eye(3) if L is None else L
                P[:, j] = off
                continue
            R[:, j] = R[:, p] if L is None else R[:, p] @ L
            Rm = R[:, j] if self._own else R[:, p]
            P[:, j] = P[:, p] + np.einsum("tab,tb->ta", Rm, off)
        P *= self.length_unit
        return P

    def position(self, frame: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """(C,) one frame -> (J, 3) metres; into ``out`` (J, 3) when given.  Compiled
        (mocap.fastfk) where lacuna.jit allows, else ``positions`` of a batch of one."""
        f = np.asarray(frame, dtype=np.float64).reshape(-1)
        if f.shape[0] != len(self.channels):
            raise ValueError(f"a frame has {len(self.channels)} values (got {f.shape[0]})")
        from lacuna import jit

        if jit.enabled():
            from mocap import fastfk

            if self._fast is None:
                self._fast = fastfk.tables(self)
                self._scratch = np.empty((len(self.joints), 3, 3))
            o = np.empty((len(self.joints), 3)) if out is None else out
            fastfk.position1(f, *self._fast, self.length_unit, self._scratch, o)
            return o
        if out is None:
            return self.positions(f.reshape(1, -1))[0]
        self.positions(f.reshape(1, -1), out.reshape(1, *out.shape))
        return out

    def rest_positions(self) -> np.ndarray:
        """(J, 3) metres with every channel 0."""
        return self.position(np.zeros(len(self.channels)))

    def segments(self) -> list[tuple[int, int]]:
        """(parent, child) joint index pairs, one per bone, for drawing."""
        return [(p, j) for j, p in enumerate(self.parents) if p >= 0]

    def affected(self, channels: np.ndarray) -> np.ndarray:
        """(..., C) bool channel mask -> (..., J) bool: joints whose position depends on a masked channel."""
        m = np.asarray(channels, dtype=bool)
        return (m.astype(np.int32) @ self.depends.T.astype(np.int32)) > 0


def _column_index(channels: list[str]) -> dict[str, int]:
    return {c: i for i, c in enumerate(channels)}


def _from_asf(skel: Any, channels: list[str], length_unit: float | None, up_axis: str | None) -> Kinematics:
    col = _column_index(channels)
    if length_unit is None:
        try:
            scale = float(skel.units.get("length", "1"))
        except ValueError:
            raise ValueError(f"{skel.source}: ':units length {skel.units.get('length')}' is not a number") from None
        length_unit = INCH_M / scale
    bones = {b.name: b for b in skel.bones}
    parent_of: dict[str, str] = {}
    for p, kids in skel.hierarchy.items():
        for k in kids:
            parent_of[k] = p
    order, seen = ["root"], {"root"}
    frontier = ["root"]
    while frontier:  # breadth first from the root: parents before children
        nxt = []
        for p in frontier:
            for k in skel.hierarchy.get(p, []):
                if k not in seen:
                    seen.add(k)
                    order.append(k)
                    nxt.append(k)
        frontier = nxt
    lost = [b.name for b in skel.bones if b.name not in seen]
    if lost:
        raise ValueError(f"{skel.source}: bones not reachable from the root in ':hierarchy': {', '.join(lost[:4])}")
    idx = {n: i for i, n in enumerate(order)}
    parents, offs, rot, trans, pre = [], [], [], [], []

    def rot_list(name: str, dofs: list[str]) -> list[tuple[int, int]]:
        r = [(col.get(f"{name}.{d}", -1), _AXES.index(d[1])) for d in dofs if d.startswith("r")]
        return list(reversed(r))  # dofs apply in listed order: M = R_last @ ... @ R_first

    for n in order:
        if n == "root":
            parents.append(-1)
            offs.append((0.0, 0.0, 0.0))
            rot.append(rot_list("root", skel.root_order))
            trans.append([(col[f"root.{d}"], _AXES.index(d[1])) for d in skel.root_order
                          if d.startswith("t") and f"root.{d}" in col])
            pre.append(np.eye(3))  # root orientation/axis: CMU's are zero; see module docstring
            continue
        b = bones[n]
        parents.append(idx[parent_of[n]])
        offs.append(tuple(float(d) * b.length for d in b.direction))
        rot.append(rot_list(n, b.dofs))
        trans.append([])
        pre.append(axis_matrix(b.axis, b.axis_order))
    return Kinematics(order, parents, channels, np.array(offs), rot, trans, np.array(pre), True,
                      length_unit, up_axis or "y", "asf")


def _from_bvh(hier: Any, channels: list[str], length_unit: float | None, up_axis: str | None,
              frames: np.ndarray | None) -> Kinematics:
    from mocap.bvh import BVH_CHANNELS

    col = _column_index(channels)
    names = [j.name for j in hier.joints]
    parents = [-1 if j.parent is None else j.parent for j in hier.joints]
    rot, trans = [], []
    for j in hier.joints:
        r, t = [], []
        for c in j.channels:
            d = BVH_CHANNELS[c]
            name = f"{j.name}.{d}"
            if d.startswith("r"):
                r.append((col.get(name, -1), _AXES.index(d[1])))
            elif name in col:
                t.append((col[name], _AXES.index(d[1])))
        rot.append(r)
        trans.append(t)
    J = len(names)
    offs = np.array([j.offset for j in hier.joints], dtype=np.float64)
    kin = Kinematics(names, parents, channels, offs, rot, trans, np.tile(np.eye(3), (J, 1, 1)), False,
                     1.0, up_axis or "y", "bvh")
    if length_unit is None:
        length_unit = guess_length_unit(kin)
    kin.length_unit = float(length_unit)
    if up_axis is None and frames is not None and len(frames):
        kin.up_axis = guess_up_axis(kin, frames)
    return kin


def _extent(P: np.ndarray) -> np.ndarray:
    """(..., J, 3) -> (..., 3) range of the joints along each axis."""
    return P.max(-2) - P.min(-2)


def guess_length_unit(kin: Kinematics) -> float:
    """The unit in BVH_UNITS that makes the rest pose's largest extent nearest 1.7 m (log scale)."""
    lu = kin.length_unit
    kin.length_unit = 1.0
    h = float(_extent(kin.rest_positions()).max())
    kin.length_unit = lu
    if h <= 0:
        return 1.0
    return min(BVH_UNITS.values(), key=lambda u: abs(math.log(h * u / TYPICAL_HEIGHT_M)))


def guess_up_axis(kin: Kinematics, frames: np.ndarray, n: int = 32) -> str:
    """The axis along which the posed skeleton is tallest, median over up to n frames spread over the take."""
    F = np.asarray(frames, dtype=np.float64)
    sel = F[np.linspace(0, len(F) - 1, min(n, len(F))).astype(int)]
    ext = np.median(_extent(kin.positions(sel)), 0)
    return _AXES[int(np.argmax(ext))]


def skeleton_record(motion: Motion) -> dict[str, Any] | None:
    """The motion's skeleton as JSON-ready text (``{"format": "bvh"|"asf", "text": ...}``), for a
    model file to carry, so whoever serves or shows the model can run FK; None without one."""
    from mocap.asf import Skeleton
    from mocap.bvh import Hierarchy, format_bvh

    sk = motion.skeleton
    if isinstance(sk, Hierarchy):
        empty = Motion(np.zeros((0, len(sk.channels))), list(sk.channels), motion.fps, sk, motion.source)
        return {"format": "bvh", "text": format_bvh(empty)}
    if isinstance(sk, Skeleton) and sk.text:
        return {"format": "asf", "text": sk.text}
    return None


def from_record(record: dict[str, Any], channels: Sequence[str] | None = None, **kw: Any) -> Kinematics:
    """Kinematics of a ``skeleton_record`` (a model file's ``meta["training"]["skeleton"]``)."""
    from mocap.asf import parse_asf
    from mocap.bvh import parse_bvh

    fmt = record.get("format")
    if fmt == "bvh":
        sk = parse_bvh(record["text"], "<model skeleton>").skeleton
    elif fmt == "asf":
        sk = parse_asf(record["text"], "<model skeleton>")
    else:
        raise ValueError(f"skeleton record format {fmt!r} is not bvh or asf")
    return Kinematics.from_skeleton(sk, list(channels) if channels is not None else None, **kw)
