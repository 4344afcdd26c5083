"""Skeleton maps (issue 20): every shipped naming is recognised from a hand-written BVH take,
its joint groups and root are found through the map, drop patterns erase the right channels,
a pattern that would erase nothing is an error naming the skeleton, and --skeleton selects a
map by name or file."""
from __future__ import annotations

import numpy as np
import pytest
from skeleton_headers import NAMINGS, bvh_text

from clients.takes import drop_mask
from lacuna.errors import LacunaError
from mocap import skelmap
from mocap.bvh import parse_bvh
from mocap.motion import Motion
from mocap.tpose import leading_tpose, skip_tpose

GROUP_BONES = {  # a bone of every group, per naming, as a studio would name it
    "humanik": {"left-arm": "LeftForeArm", "right-leg": "RightLeg", "head-neck": "Head", "torso": "Spine1"},
    "vicon-shogun": {"left-arm": "LeftForeArm", "right-leg": "RightLeg", "head-neck": "Neck1", "torso": "Spine3"},
    "optitrack-motive": {"left-arm": "LFArm", "right-leg": "RShin", "head-neck": "Neck", "torso": "Ab"},
    "xsens-mvn": {"left-arm": "LeftElbow", "right-leg": "RightKnee", "head-neck": "Head", "torso": "Chest2"},
    "cmu-bvh": {"left-arm": "LeftForeArm", "right-leg": "RightLeg", "head-neck": "Neck1", "torso": "LowerBack"},
}


@pytest.mark.parametrize("naming", sorted(NAMINGS))
def test_each_naming_is_recognised_with_its_groups_and_root(naming):
    chain = NAMINGS[naming]()
    m = parse_bvh(bvh_text(chain, 60), f"{naming}.bvh")
    b = skelmap.Binding.of(m.channels, source=m.source)
    assert b.map.name == naming
    pre = chain["prefix"]
    for g, bone in GROUP_BONES[naming].items():
        assert pre + bone in b.bones(g), (g, b.bones(g))
    root = pre + chain["spec"][0][0]
    assert b.root_bone == root
    spec = b.root_spec(m.skeleton)
    assert spec["rot"] == [f"{root}.rx", f"{root}.ry", f"{root}.rz"]
    assert spec["pos"] == [f"{root}.tx", f"{root}.ty", f"{root}.tz"]
    assert spec["order"] == "".join(w[0].lower() for w in chain["root_rot"].split())
    # every channel but the root's belongs to a joint group
    assert all(p in skelmap.GROUPS for c, p in zip(m.channels, b.parts) if not c.startswith(root + "."))


@pytest.mark.parametrize("naming", sorted(NAMINGS))
def test_drop_patterns_erase_that_namings_groups(naming):
    chain = NAMINGS[naming]()
    m = parse_bvh(bvh_text(chain, 1200), f"{naming}.bvh")
    b = skelmap.Binding.of(m.channels)
    obs, bursts = drop_mask("gaps:left-arm", m, 3)
    arm = b.mask("left-arm")
    assert bursts and (~obs[:, arm]).any() and obs[:, ~arm].all()
    obs, _ = drop_mask("pan2009", m)
    legs = b.mask("legs")
    T = m.n_frames
    assert obs[:, legs].all() and not obs[T // 2:, ~legs].any() and obs[: T // 2].all()
    obs, _ = drop_mask("taylor2007:upper-body", m)
    assert not obs[T // 2:, b.mask("upper-body")].any() and obs[:, b.mask(["legs", "root"])].all()


def test_a_drop_that_would_erase_nothing_names_the_skeleton_and_groups():
    # a take of legs only: its arms are not there to erase
    legs = [f"{j}.{d}" for j in ("LeftUpLeg", "LeftLeg", "RightUpLeg", "RightLeg", "Hips") for d in ("rx", "ry", "rz")]
    m = Motion(np.zeros((300, len(legs))), legs, 120.0, source="legs.bvh")
    with pytest.raises(LacunaError, match=r"--drop gaps:left-arm: legs.bvh \(skeleton [\w-]+\) has no channels in "
                                          r"left-arm: looked for bones .*LeftArm"):
        drop_mask("gaps:left-arm", m)


def test_unknown_bones_are_a_clear_error_and_skeleton_selects_a_map(tmp_path):
    ch = ["Pelvis.rx", "Thing.ry", "Other.rz"]
    with pytest.raises(LacunaError, match=r"x.bvh: its bones \(Pelvis, Thing, Other\) match no known skeleton"):
        skelmap.Binding.of(ch, source="x.bvh")
    with pytest.raises(LacunaError, match="--skeleton nope: unknown skeleton"):
        skelmap.load("nope")
    p = tmp_path / "studio.toml"
    p.write_text('name = "studio"\nformat = "bvh"\nup = "y"\n[root]\nbone = "Pelvis"\n'
                 '[bones]\nPelvis = { part = "root" }\nThing = { part = "left-arm", side = "left" }\n'
                 'Other = { part = "right-leg", side = "right" }\n')
    b = skelmap.Binding.of(ch, str(p))
    assert b.map.name == "studio" and b.parts == ["root", "left-arm", "right-leg"]
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "bad"\n[root]\nbone = "Pelvis"\n[bones]\nPelvis = { part = "tail" }\n')
    with pytest.raises(LacunaError, match="bone 'Pelvis': unknown part 'tail'"):
        skelmap.load(str(bad))


def test_cmu_asf_map_gives_the_protocols_groups():
    from mocap.protocols import JOINT_GROUPS

    assert JOINT_GROUPS["left-arm"] == ("lclavicle", "lhumerus", "lradius", "lwrist", "lhand", "lfingers", "lthumb")
    assert JOINT_GROUPS["right-leg"] == ("rfemur", "rtibia", "rfoot", "rtoes")
    assert JOINT_GROUPS["torso"] == ("lowerback", "upperback", "thorax")
    assert JOINT_GROUPS["head-neck"] == ("lowerneck", "upperneck", "head")


def test_every_shipped_map_loads_and_names_a_known_part():
    for name in skelmap.available():
        m = skelmap.load(name)
        assert m.bones[m.root_bone].part == "root"
        assert {i.part for i in m.bones.values()} == set(skelmap.PARTS), name


def test_leading_tpose_is_found_and_skipped():
    chain = NAMINGS["cmu-bvh"]()
    m = parse_bvh(bvh_text(chain, 120, tpose=True), "t.bvh")
    assert leading_tpose(m.frames, m.channels)
    s = skip_tpose(m, quiet=True)
    assert s.n_frames == m.n_frames - 1 and s.meta["tpose_skipped"] == 1
    assert not leading_tpose(s.frames, s.channels)
    assert skip_tpose(s, quiet=True) is s


@pytest.mark.realdata
def test_real_cmu_takes_are_recognised_and_bvh_tpose_found(data):
    from mocap.io import read_motion

    for f in ("07_01", "08_02", "09_11"):
        m = read_motion(data / "bvh" / f"{f}.bvh")
        assert skelmap.Binding.of(m.channels).map.name == "cmu-bvh"
        assert leading_tpose(m.frames, m.channels)
    a = read_motion(data / "cmu" / "07" / "07_01.amc")
    assert skelmap.Binding.of(a.channels).map.name == "cmu-asf"
    assert not leading_tpose(a.frames, a.channels)
