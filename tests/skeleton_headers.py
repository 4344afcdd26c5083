"""Small hand-written BVH takes in the namings of the systems Lacuna's skeleton maps know
(issue 20): HumanIK/Mixamo (with its ``mixamorig:`` prefix), Vicon Shogun, OptiTrack Motive,
Xsens MVN, and CMU's BVH conversion.  Each is a real BVH file (parsed by mocap.bvh) with a
walking-like motion: sinusoidal joint angles and a root moving forward, so fills have
something to learn."""
from __future__ import annotations

import math

# (name, parent, offset, channels or None for an End Site)
ROT_ZXY = "Zrotation Xrotation Yrotation"
ROT_ZYX = "Zrotation Yrotation Xrotation"


def _chain(prefix: str, spec: list[tuple[str, str, tuple[float, float, float]]], root_rot: str, rot: str,
           root_rest: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> dict:
    return {"prefix": prefix, "spec": spec, "root_rot": root_rot, "rot": rot, "rest": root_rest}


def _limb(side: str, names: list[str], parent: str, first: tuple[float, float, float], down: float,
          end: bool = True) -> list[tuple[str, str, tuple[float, float, float]]]:
    out = []
    p = parent
    for k, n in enumerate(names):
        off = first if k == 0 else (0.0, down, 0.0)
        out.append((n, p, off))
        p = n
    if end:
        out.append((f"{p}_End", p, (0.0, down * 0.5, 0.0)))
    return out


def humanik(prefix: str = "mixamorig:") -> dict:
    s = [("Hips", "", (0.0, 0.0, 0.0))]
    s += _limb("c", ["Spine", "Spine1", "Spine2", "Neck", "Head"], "Hips", (0.0, 10.0, 0.0), 10.0)
    s += _limb("l", ["LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand"], "Spine2", (5.0, 8.0, 0.0), -12.0)
    s += _limb("r", ["RightShoulder", "RightArm", "RightForeArm", "RightHand"], "Spine2", (-5.0, 8.0, 0.0), -12.0)
    s += _limb("l", ["LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase"], "Hips", (9.0, -5.0, 0.0), -40.0)
    s += _limb("r", ["RightUpLeg", "RightLeg", "RightFoot", "RightToeBase"], "Hips", (-9.0, -5.0, 0.0), -40.0)
    return _chain(prefix, s, ROT_ZXY, ROT_ZXY)


def vicon(prefix: str = "Actor1:") -> dict:
    s = [("Hips", "", (0.0, 0.0, 0.0))]
    s += _limb("c", ["Spine", "Spine1", "Spine2", "Spine3", "Neck", "Neck1", "Head"], "Hips", (0.0, 100.0, 0.0), 90.0)
    s += _limb("l", ["LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand"], "Spine3", (50.0, 80.0, 0.0), -120.0)
    s += _limb("r", ["RightShoulder", "RightArm", "RightForeArm", "RightHand"], "Spine3", (-50.0, 80.0, 0.0), -120.0)
    s += _limb("l", ["LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase"], "Hips", (90.0, -50.0, 0.0), -400.0)
    s += _limb("r", ["RightUpLeg", "RightLeg", "RightFoot", "RightToeBase"], "Hips", (-90.0, -50.0, 0.0), -400.0)
    return _chain(prefix, s, ROT_ZYX, ROT_ZYX)


def motive(prefix: str = "Skeleton_") -> dict:
    s = [("Hip", "", (0.0, 0.0, 0.0))]
    s += _limb("c", ["Ab", "Chest", "Neck", "Head"], "Hip", (0.0, 10.0, 0.0), 12.0)
    s += _limb("l", ["LShoulder", "LUArm", "LFArm", "LHand"], "Chest", (5.0, 10.0, 0.0), -12.0)
    s += _limb("r", ["RShoulder", "RUArm", "RFArm", "RHand"], "Chest", (-5.0, 10.0, 0.0), -12.0)
    s += _limb("l", ["LThigh", "LShin", "LFoot", "LToe"], "Hip", (9.0, -5.0, 0.0), -40.0)
    s += _limb("r", ["RThigh", "RShin", "RFoot", "RToe"], "Hip", (-9.0, -5.0, 0.0), -40.0)
    return _chain(prefix, s, ROT_ZXY, ROT_ZXY)


def xsens(prefix: str = "") -> dict:
    s = [("Hips", "", (0.0, 0.0, 0.0))]
    s += _limb("c", ["Chest", "Chest2", "Chest3", "Chest4", "Neck", "Head"], "Hips", (0.0, 10.0, 0.0), 8.0)
    s += _limb("l", ["LeftCollar", "LeftShoulder", "LeftElbow", "LeftWrist"], "Chest4", (4.0, 8.0, 0.0), -12.0)
    s += _limb("r", ["RightCollar", "RightShoulder", "RightElbow", "RightWrist"], "Chest4", (-4.0, 8.0, 0.0), -12.0)
    s += _limb("l", ["LeftHip", "LeftKnee", "LeftAnkle", "LeftToe"], "Hips", (9.0, -5.0, 0.0), -40.0)
    s += _limb("r", ["RightHip", "RightKnee", "RightAnkle", "RightToe"], "Hips", (-9.0, -5.0, 0.0), -40.0)
    return _chain(prefix, s, ROT_ZXY, ROT_ZXY)


def cmu_bvh(prefix: str = "") -> dict:
    s = [("Hips", "", (0.0, 0.0, 0.0))]
    s += _limb("l", ["LHipJoint", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase"], "Hips", (0.0, 0.0, 0.0), 7.0)
    s += _limb("r", ["RHipJoint", "RightUpLeg", "RightLeg", "RightFoot", "RightToeBase"], "Hips", (0.0, 0.0, 0.0), 7.0)
    s += _limb("c", ["LowerBack", "Spine", "Spine1", "Neck", "Neck1", "Head"], "Hips", (0.0, 0.0, 0.0), 2.0)
    s += _limb("l", ["LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand"], "Spine1", (0.0, 0.0, 0.0), 3.5)
    s += _limb("r", ["RightShoulder", "RightArm", "RightForeArm", "RightHand"], "Spine1", (0.0, 0.0, 0.0), 3.5)
    return _chain(prefix, s, ROT_ZYX, ROT_ZYX, (90.0, 0.0, 0.0))


NAMINGS = {"humanik": humanik, "vicon-shogun": vicon, "optitrack-motive": motive, "xsens-mvn": xsens,
           "cmu-bvh": cmu_bvh}


def bvh_text(chain: dict, n_frames: int = 240, fps: float = 120.0, tpose: bool = False) -> str:
    """BVH text of the chain with a walking-like motion (and a leading T-pose when asked)."""
    pre, spec = chain["prefix"], chain["spec"]
    kids: dict[str, list[int]] = {}
    for i, (_n, p, _) in enumerate(spec):
        kids.setdefault(p, []).append(i)
    lines = ["HIERARCHY"]
    cols: list[tuple[str, str]] = []  # (joint, channel)

    def node(i: int, depth: int) -> None:
        n, p, off = spec[i]
        ind = "  " * depth
        if n.endswith("_End"):
            lines.extend([f"{ind}End Site", f"{ind}{{", f"{ind}  OFFSET {off[0]} {off[1]} {off[2]}", f"{ind}}}"])
            return
        lines.append(f"{ind}{'ROOT' if not p else 'JOINT'} {pre}{n}")
        lines.append(f"{ind}{{")
        lines.append(f"{ind}  OFFSET {off[0]} {off[1]} {off[2]}")
        chans = (["Xposition", "Yposition", "Zposition"] + chain["root_rot"].split()) if not p else chain["rot"].split()
        lines.append(f"{ind}  CHANNELS {len(chans)} {' '.join(chans)}")
        cols.extend((n, c) for c in chans)
        for k in kids.get(n, []):
            node(k, depth + 1)
        lines.append(f"{ind}}}")

    node(0, 0)
    rows = []
    for t in range(-1 if tpose else 0, n_frames):
        ph = 2 * math.pi * max(t, 0) / fps  # one stride a second
        row = []
        for j, (n, c) in enumerate(cols):
            if t < 0:  # T-pose: everything at rest, the root upright where it starts
                v = 0.0 if "rotation" in c else {"X": 0.0, "Y": 90.0, "Z": 0.0}[c[0]]
                if n == spec[0][0] and "rotation" in c:
                    v = chain["rest"]["XYZ".index(c[0])]
            elif "position" in c:
                v = {"X": 0.0, "Y": 90.0 + 2 * math.sin(2 * ph), "Z": 100.0 * max(t, 0) / fps}[c[0]]
            elif n == spec[0][0]:
                v = chain["rest"]["XYZ".index(c[0])] + 3.0 * math.sin(ph + j)
            else:
                v = (40.0 if "Leg" in n or "Thigh" in n or "Hip" in n or "Knee" in n else 10.0) * math.sin(ph + 0.7 * j)
            row.append(f"{v:.6f}")
        rows.append(" ".join(row))
    lines += ["MOTION", f"Frames: {len(rows)}", f"Frame Time: {1.0 / fps:.7f}"] + rows
    return "\n".join(lines) + "\n"
