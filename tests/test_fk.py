"""Forward kinematics against positions computed independently of mocap.fk (issue 20).

BVH: the offset chain written out by hand with explicit rotation matrices, on a hand-written
header and on frames of a real CMU BVH take.  ASF: the Acclaim convention C M C^-1 computed with
scipy's Euler code and a hand-written skeleton, and the AMC -> FK -> AMC round trip.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocap.asf import format_amc, parse_amc, parse_asf, read_asf
from mocap.bvh import parse_bvh, read_bvh
from mocap.fk import Kinematics
from mocap.io import read_motion

TOL_M = 1e-6


def Rx(a):
    a = math.radians(a)
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


def Ry(a):
    a = math.radians(a)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def Rz(a):
    a = math.radians(a)
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


HAND_BVH = """HIERARCHY
ROOT Hips
{
  OFFSET 1 2 3
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Spine
  {
    OFFSET 0 10 0
    CHANNELS 3 Yrotation Xrotation Zrotation
    JOINT Head
    {
      OFFSET 0 5 1
      CHANNELS 3 Xrotation Zrotation Yrotation
      End Site
      {
        OFFSET 0 3 0
      }
    }
  }
  JOINT LeftUpLeg
  {
    OFFSET 4 -1 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    End Site
    {
      OFFSET 0 -40 0
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.01
0 0 0 0 0 0 0 0 0 0 0 0 0 0 0
5 90 -3 30 -20 45 10 20 30 -15 25 60 80 -35 12
-2 88 7 170 65 -130 -95 14 3 120 -170 45 3 88 -60
"""


def _hand_positions(f):
    """The HAND_BVH chain written out: p_child = p_parent + R_parent @ offset, R = product of
    the joint's rotations in the order its CHANNELS line declares them."""
    R_hips = Rz(f[3]) @ Rx(f[4]) @ Ry(f[5])
    p_hips = np.array([1, 2, 3]) + f[0:3]
    R_spine = R_hips @ Ry(f[6]) @ Rx(f[7]) @ Rz(f[8])
    p_spine = p_hips + R_hips @ [0, 10, 0]
    R_head = R_spine @ Rx(f[9]) @ Rz(f[10]) @ Ry(f[11])
    p_head = p_spine + R_spine @ [0, 5, 1]
    p_head_end = p_head + R_head @ [0, 3, 0]
    R_leg = R_hips @ Rz(f[12]) @ Ry(f[13]) @ Rx(f[14])
    p_leg = p_hips + R_hips @ [4, -1, 0]
    p_leg_end = p_leg + R_leg @ [0, -40, 0]
    return {"Hips": p_hips, "Spine": p_spine, "Head": p_head, "Head_End": p_head_end,
            "LeftUpLeg": p_leg, "LeftUpLeg_End": p_leg_end}


def test_bvh_hand_written_header_matches_the_chain_by_hand():
    m = parse_bvh(HAND_BVH)
    kin = Kinematics.from_motion(m, length_unit=0.01)
    assert kin.joints == ["Hips", "Spine", "Head", "Head_End", "LeftUpLeg", "LeftUpLeg_End"]
    assert kin.parents == [-1, 0, 1, 2, 0, 4]
    assert kin.segments() == [(0, 1), (1, 2), (2, 3), (0, 4), (4, 5)]
    P = kin.positions(m.frames)
    for t in range(m.n_frames):
        want = _hand_positions(m.frames[t])
        for j, name in enumerate(kin.joints):
            np.testing.assert_allclose(P[t, j], want[name] * 0.01, atol=TOL_M, rtol=0)
        np.testing.assert_allclose(kin.position(m.frames[t]), P[t], atol=1e-12, rtol=0)


def test_bvh_dependencies_follow_the_chain():
    m = parse_bvh(HAND_BVH)
    kin = Kinematics.from_motion(m, length_unit=1.0)
    head_rot = np.array([c.startswith("Head.") for c in m.channels])
    # the Head's own rotation moves only its End Site; the spine's moves the head and beyond
    assert [kin.joints[j] for j in np.flatnonzero(kin.affected(head_rot))] == ["Head_End"]
    spine = np.array([c.startswith("Spine.") for c in m.channels])
    assert [kin.joints[j] for j in np.flatnonzero(kin.affected(spine))] == ["Head", "Head_End"]
    # and the dependency is real: changing a Spine angle moves exactly those joints
    f = m.frames[1].copy()
    g = f.copy()
    g[m.channels.index("Spine.rx")] += 10
    moved = np.linalg.norm(kin.position(g) - kin.position(f), axis=1) > 1e-9
    assert (moved == kin.affected(spine)).all()


@pytest.mark.realdata
def test_bvh_real_take_left_leg_by_hand(data):
    """08_02.bvh (CMU, channels Zrotation Yrotation Xrotation): Hips -> LHipJoint -> LeftUpLeg
    -> LeftLeg -> LeftFoot -> LeftToeBase -> End Site, chained by hand from the file's offsets."""
    m = read_bvh(data / "bvh" / "08_02.bvh")
    H = m.skeleton
    chain = ["Hips", "LHipJoint", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase", "LeftToeBase_End"]
    off = {j.name: np.array(j.offset) for j in H.joints}
    kin = Kinematics.from_motion(m)
    assert kin.length_unit == pytest.approx(0.0254 / 0.45)  # CMU BVH: ASF units (see test below)
    idx = [kin.joints.index(n) for n in chain]
    for t in (0, 1, 97, 200, m.n_frames - 1):
        f = m.frames[t]

        def ang(joint):
            return [f[m.channels.index(f"{joint}.{d}")] for d in ("rz", "ry", "rx")]

        p = f[m.index(["Hips.tx", "Hips.ty", "Hips.tz"])] + off["Hips"]
        R = np.eye(3)
        want = []
        for k, n in enumerate(chain):
            if k:
                p = p + R @ off[n]
            want.append(p)
            if n != chain[-1]:
                z, y, x = ang(n)
                R = R @ Rz(z) @ Ry(y) @ Rx(x)
        got = kin.position(f)[idx]
        np.testing.assert_allclose(got, np.array(want) * kin.length_unit, atol=TOL_M, rtol=0)


HAND_ASF = """:version 1.10
:name hand
:units
  mass 1.0
  length 0.45
  angle deg
:root
   order TX TY TZ RX RY RZ
   axis XYZ
   position 0 0 0
   orientation 0 0 0
:bonedata
  begin
     id 1
     name thigh
     direction 0.34202 -0.939693 0
     length 7
     axis 0 0 20  XYZ
    dof rx ry rz
  end
  begin
     id 2
     name shin
     direction 0 -1 0
     length 6
     axis 10 -30 40  ZYX
    dof rz rx
  end
  begin
     id 3
     name foot
     direction 0 0 1
     length 2
     axis -90 7 0  XYZ
    dof ry
  end
:hierarchy
  begin
    root thigh
    thigh shin
    shin foot
  end
"""


def _scipy_matrix(angles_by_axis, order):
    """Acclaim: rotations apply in the listed order, i.e. R = R_last @ ... @ R_first; scipy's
    intrinsic Euler sequence 'ZYX' is exactly Rz @ Ry @ Rx."""
    seq = order.upper()[::-1]
    return Rotation.from_euler(seq, [angles_by_axis[a] for a in seq.lower()], degrees=True).as_matrix()


def _asf_by_hand(skel, frame, channels):
    """Independent Acclaim FK: R_b = R_parent C M C^-1, p_b = p_parent + R_b (length * direction)."""
    v = dict(zip(channels, frame))
    root_rot = {d[1]: v[f"root.{d}"] for d in skel.root_order if d.startswith("r")}
    rorder = "".join(d[1] for d in skel.root_order if d.startswith("r"))
    R = {"root": _scipy_matrix(root_rot, rorder)}
    P = {"root": np.array([v["root.tx"], v["root.ty"], v["root.tz"]])}
    parent = {k: p for p, ks in skel.hierarchy.items() for k in ks}
    todo = [b for b in skel.bones]
    while todo:
        b = todo.pop(0)
        if parent[b.name] not in R:
            todo.append(b)
            continue
        C = _scipy_matrix(dict(zip("xyz", b.axis)), b.axis_order)
        rots = {d[1]: v[f"{b.name}.{d}"] for d in b.dofs if d.startswith("r")}
        M = _scipy_matrix({**{"x": 0, "y": 0, "z": 0}, **rots}, "".join(d[1] for d in b.dofs if d.startswith("r")) or "x")
        R[b.name] = R[parent[b.name]] @ C @ M @ C.T
        P[b.name] = P[parent[b.name]] + R[b.name] @ (b.length * np.array(b.direction))
    return P


def test_asf_hand_written_skeleton_matches_acclaim_by_hand():
    skel = parse_asf(HAND_ASF)
    rng = np.random.default_rng(20)
    frames = rng.uniform(-170, 170, (5, len(skel.channels)))
    frames[:, :3] = rng.uniform(-20, 20, (5, 3))
    kin = Kinematics.from_skeleton(skel)
    assert kin.length_unit == pytest.approx(0.0254 / 0.45)
    P = kin.positions(frames)
    for t in range(5):
        want = _asf_by_hand(skel, frames[t], skel.channels)
        for j, n in enumerate(kin.joints):
            np.testing.assert_allclose(P[t, j], want[n] * kin.length_unit, atol=TOL_M, rtol=0)


@pytest.mark.realdata
def test_asf_real_take_matches_acclaim_by_hand_and_survives_a_round_trip(data):
    m = read_motion(data / "cmu" / "07" / "07_01.amc")
    kin = Kinematics.from_motion(m)
    P = kin.positions(m.frames)
    for t in (0, 150, m.n_frames - 1):
        want = _asf_by_hand(m.skeleton, m.frames[t], m.channels)
        for j, n in enumerate(kin.joints):
            np.testing.assert_allclose(P[t, j], want[n] * kin.length_unit, atol=TOL_M, rtol=0)
    # AMC text -> motion -> FK: the written file gives the same positions
    back = parse_amc(format_amc(m), m.skeleton)
    np.testing.assert_allclose(Kinematics.from_motion(back).positions(back.frames), P, atol=TOL_M, rtol=0)


@pytest.mark.realdata
def test_asf_walk_sanity_feet_on_floor_bones_rigid(data):
    m = read_motion(data / "cmu" / "07" / "07_01.amc")
    kin = Kinematics.from_motion(m)
    P = kin.positions(m.frames)
    up = "xyz".index(kin.up_axis)
    toes = [kin.joints.index(n) for n in ("ltoes", "rtoes")]
    lowest = P[:, toes, up].min(1)
    assert np.percentile(lowest, 10) < 0.05 and lowest.min() > -0.05  # a foot is on the floor
    head = P[:, kin.joints.index("head"), up]
    assert 1.4 < head.mean() < 1.9  # a standing adult, in metres
    for p, c in kin.segments():
        L = np.linalg.norm(P[:, c] - P[:, p], axis=1)
        assert np.ptp(L) < 1e-9


@pytest.mark.realdata
def test_cmu_bvh_and_asf_of_the_same_take_agree_on_the_legs(data):
    """07_01 as AMC and as CMU's BVH: BVH frame t+1 is AMC frame t (BVH frame 0 is an added
    T-pose), BVH is Z-up (x, y, z)_bvh = (x, -z, y)_asf, and its lengths are the ASF's units
    (offsets equal the ASF bone lengths): the leg joints coincide within the BVH's 4-decimal
    rounding.  (The upper body does not: CMU's BVH drops the thorax length.)"""
    a = read_motion(data / "cmu" / "07" / "07_01.amc")
    b = read_motion(data / "bvh" / "07_01.bvh")
    ka, kb = Kinematics.from_motion(a), Kinematics.from_motion(b)
    assert kb.up_axis == "z" and kb.length_unit == pytest.approx(ka.length_unit)
    Pa = ka.positions(a.frames)
    Pb = kb.positions(b.frames[1:])
    Pb = np.stack([Pb[..., 0], Pb[..., 2], -Pb[..., 1]], -1)
    pairs = {"root": "Hips", "lhipjoint": "LeftUpLeg", "lfemur": "LeftLeg", "ltibia": "LeftFoot",
             "lfoot": "LeftToeBase", "ltoes": "LeftToeBase_End", "rtibia": "RightFoot"}
    for an, bn in pairs.items():
        d = np.linalg.norm(Pa[:, ka.joints.index(an)] - Pb[:, kb.joints.index(bn)], axis=1)
        assert d.max() < 0.005, (an, bn, d.max())


def test_csv_motion_without_skeleton_is_a_clear_error():
    from mocap.motion import Motion

    with pytest.raises(ValueError, match="no skeleton"):
        Kinematics.from_motion(Motion(np.zeros((2, 1)), ["a.rx"], source="x.csv"))


@pytest.mark.realdata
def test_asf_skeleton_of_a_real_subject_loads_every_bone(data):
    skel = read_asf(data / "cmu" / "35" / "35.asf")
    kin = Kinematics.from_skeleton(skel)
    assert set(kin.joints) == {"root"} | {b.name for b in skel.bones}
    assert kin.depends.shape == (len(kin.joints), len(skel.channels))


def test_joint_position_error_counts_only_joints_an_erased_value_moves():
    from mocap.fkerror import joint_errors_cm, joint_position_error

    m = parse_bvh(HAND_BVH)
    kin = Kinematics.from_motion(m, length_unit=0.01)  # centimetres
    truth = m.frames
    filled = truth.copy()
    erased = np.zeros(truth.shape, bool)
    j = m.channels.index("LeftUpLeg.rx")
    erased[1, j] = True
    filled[1, j] += 10.0  # the fill is 10 degrees off on the leg, frame 1
    e = joint_errors_cm(kin, truth, filled, erased)
    # only the leg's End Site moves: |R_hips Rz Ry (Rx(a + 10) - Rx(a)) (0, -40, 0)| cm
    f = truth[1]
    R = Rz(f[3]) @ Rx(f[4]) @ Ry(f[5]) @ Rz(f[12]) @ Ry(f[13])
    want = np.linalg.norm(R @ (Rx(f[14] + 10) - Rx(f[14])) @ [0, -40, 0])
    np.testing.assert_allclose(e, [want], atol=1e-9)
    s = joint_position_error(kin, truth, filled, erased)
    assert s["n"] == 1 and s["mean_cm"] == pytest.approx(want)
    # a root translation erased on frame 2 moves every joint by the same offset
    erased[2, m.channels.index("Hips.tx")] = True
    filled[2, m.channels.index("Hips.tx")] += 3.0
    e = joint_errors_cm(kin, truth, filled, erased)
    np.testing.assert_allclose(e[1:], np.full(len(kin.joints), 3.0), atol=1e-9)


@pytest.mark.realdata
def test_per_frame_position_equals_the_batch(data, monkeypatch):
    """position() is compiled (mocap.fastfk) where numba may run; both paths equal positions()."""
    from lacuna import jit

    for f in (data / "cmu" / "07" / "07_01.amc", data / "bvh" / "08_02.bvh"):
        m = read_motion(f)
        P = Kinematics.from_motion(m).positions(m.frames[::25])
        for on in (True, False):
            monkeypatch.setattr(jit, "enabled", lambda on=on: on)
            kin = Kinematics.from_motion(m)
            out = np.empty((len(kin.joints), 3))
            for t, fr in enumerate(m.frames[::25]):
                assert kin.position(fr, out) is out
                np.testing.assert_allclose(out, P[t], atol=1e-12, rtol=0)
