"""``default`` on every shipped skeleton naming (issues 17 and 20): its joint groups come from the
skeleton map, so a BVH take of any naming trains and fills by body part, never all "other".

The takes are CMU's real 07_01 / 08_02 BVH (``../shared/data/bvh``) with their bones renamed to
each naming (a few hundred frames written to tmp_path; nothing is committed), and a real AMC take
for cmu-asf.  07_01 is a papers' test take: it is only filled here, never tuned on."""
from __future__ import annotations

import json

import numpy as np
import pytest

from blend.groups import GROUP_NAMES, OTHER, ROOT_POS, legacy_groups
from clients.harness import DaemonProcess
from clients.takes import drop_mask
from lacuna import modelfile
from lacuna.cli import main
from mocap import skelmap
from mocap.bvh import BVH_CHANNELS, Hierarchy, Joint, write_bvh
from mocap.io import read_motion
from mocap.motion import Motion
from mocap.representation import circular_mean_deg, is_angle, wrap180
from mocap.tpose import skip_tpose

pytestmark = pytest.mark.realdata

# CMU BVH bone -> the naming's bone ("" = the joint is removed: a still hip joint spliced out, or a
# finger subtree dropped); {S}/{s} = Left/Right, L/R
RENAME: dict[str, dict[str, str]] = {
    "humanik": {"Hips": "mixamorig:Hips", "LowerBack": "mixamorig:Spine", "Spine": "mixamorig:Spine1",
                "Spine1": "mixamorig:Spine2", "Neck": "mixamorig:Neck", "Neck1": "mixamorig:Neck1",
                "Head": "mixamorig:Head", "{s}HipJoint": "", "Left*": "mixamorig:{S}*", "Right*": "mixamorig:{S}*",
                "{S}FingerBase": "mixamorig:{S}HandMiddle1", "{S}HandIndex1": "mixamorig:{S}HandIndex1",
                "{s}Thumb": "mixamorig:{S}HandThumb1"},
    "vicon-shogun": {"Hips": "Actor1:Hips", "LowerBack": "Actor1:Spine1", "Spine": "Actor1:Spine2",
                     "Spine1": "Actor1:Spine3", "Neck": "Actor1:Neck", "Neck1": "Actor1:Neck1", "Head": "Actor1:Head",
                     "{s}HipJoint": "", "Left*": "Actor1:{S}*", "Right*": "Actor1:{S}*",
                     "{S}FingerBase": "Actor1:{S}HandMiddle1", "{S}HandIndex1": "Actor1:{S}HandIndex1",
                     "{s}Thumb": "Actor1:{S}HandThumb1"},
    "optitrack-motive": {"Hips": "Skeleton_Hip", "LowerBack": "Skeleton_Ab", "Spine": "", "Spine1": "Skeleton_Chest",
                         "Neck": "Skeleton_Neck", "Neck1": "", "Head": "Skeleton_Head", "{s}HipJoint": "",
                         "{S}UpLeg": "Skeleton_{s}Thigh", "{S}Leg": "Skeleton_{s}Shin", "{S}Foot": "Skeleton_{s}Foot",
                         "{S}ToeBase": "Skeleton_{s}Toe", "{S}Shoulder": "Skeleton_{s}Shoulder",
                         "{S}Arm": "Skeleton_{s}UArm", "{S}ForeArm": "Skeleton_{s}FArm", "{S}Hand": "Skeleton_{s}Hand",
                         "{S}FingerBase": "Skeleton_{s}Index1", "{S}HandIndex1": "Skeleton_{s}Index2",
                         "{s}Thumb": "Skeleton_{s}Thumb1"},
    "xsens-mvn": {"Hips": "Hips", "LowerBack": "Chest", "Spine": "Chest2", "Spine1": "Chest4", "Neck": "Neck",
                  "Neck1": "", "Head": "Head", "{s}HipJoint": "", "{S}UpLeg": "{S}Hip", "{S}Leg": "{S}Knee",
                  "{S}Foot": "{S}Ankle", "{S}ToeBase": "{S}Toe", "{S}Shoulder": "{S}Collar", "{S}Arm": "{S}Shoulder",
                  "{S}ForeArm": "{S}Elbow", "{S}Hand": "{S}Wrist", "{S}FingerBase": "", "{S}HandIndex1": "",
                  "{s}Thumb": ""},
    "cmu-bvh": {},
}
BVH_NAMINGS = sorted(RENAME)


def _target(naming: str, bone: str) -> str:
    table = RENAME[naming]
    for side, s in (("Left", "L"), ("Right", "R")):
        for k, v in table.items():
            if "{" in k and k.replace("{S}", side).replace("{s}", s) == bone:
                return v.replace("{S}", side).replace("{s}", s)
    if bone in table:
        return table[bone]
    for side in ("Left", "Right"):
        if f"{side}*" in table and bone.startswith(side):
            return table[f"{side}*"].replace("{S}", side).replace("*", bone[len(side):])
    return bone


def converted(data, take: str, naming: str, path, n_frames: int = 300) -> Motion:
    """CMU's BVH of ``take`` with its bones renamed to ``naming`` and the joints it lacks removed
    (a still joint's children keep their place: its offset is added to theirs), written to ``path``."""
    m = skip_tpose(read_motion(data / "bvh" / f"{take}.bvh"), quiet=True)
    hier = m.skeleton
    assert isinstance(hier, Hierarchy)
    finger = ("FingerBase", "HandIndex1", "Thumb")
    keep: dict[int, str] = {}
    new_index: dict[int, int] = {}
    gone: set[int] = set()      # finger subtrees dropped
    spliced: set[int] = set()   # joints removed, their children attached to their parent
    joints: list[Joint] = []
    for i, j in enumerate(hier.joints):
        name = j.name if j.kind == "End Site" else _target(naming, j.name)
        if j.parent in gone or (name == "" and j.name.endswith(finger)):
            gone.add(i)
            continue
        if name == "":
            spliced.add(i)
            continue
        parent, off = j.parent, np.array(j.offset, float)
        while parent in spliced:
            off = off + np.array(hier.joints[parent].offset, float)
            parent = hier.joints[parent].parent
        new_index[i] = len(joints)
        joints.append(Joint(name, j.kind, tuple(off), list(j.channels), None if parent is None else new_index[parent]))
        keep[i] = name
    for i, j in enumerate(list(joints)):  # a joint whose fingers were dropped ends in an End Site
        if j.kind != "End Site" and not any(k.parent == i for k in joints):
            joints.append(Joint("", "End Site", (0.0, 0.0, 0.0), [], i))
    cols, names = [], []
    for i, j in enumerate(hier.joints):
        for c in j.channels:
            if i in keep:
                cols.append(m.channels.index(f"{j.name}.{BVH_CHANNELS[c]}"))
                names.append(f"{keep[i]}.{BVH_CHANNELS[c]}")
    out = Motion(m.frames[:n_frames, cols], names, m.fps, Hierarchy(joints, str(path)), str(path))
    write_bvh(path, out)
    return read_motion(path)


def _hold(frames: np.ndarray, observed: np.ndarray) -> np.ndarray:
    h = frames.copy()
    for t in range(1, len(h)):
        h[t] = np.where(observed[t], frames[t], h[t - 1])
    return h


def _fill(model, frames: np.ndarray, observed: np.ndarray) -> np.ndarray:
    st = model.stream()
    return np.array([st.step(np.where(o, f, np.nan), o).frame for f, o in zip(frames, observed)])


@pytest.mark.parametrize("naming", BVH_NAMINGS)
def test_default_trains_and_fills_by_body_part_on_each_bvh_naming(naming, data, tmp_path, capsys):
    converted(data, "08_02", naming, tmp_path / "train.bvh")
    test = converted(data, "07_01", naming, tmp_path / "test.bvh")
    b = skelmap.Binding.of(test.channels)
    assert b.map.name == naming  # recognised from the bone names alone
    out = tmp_path / "m.npz"
    assert main(["train", "default-blend", str(tmp_path / "train.bvh"), "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"({naming})" in err and "warning" not in err
    model = modelfile.load_model(str(out))
    meta, arrays = modelfile.load_arrays(str(out))
    assert meta["skeleton_map"] == naming and arrays["group"].tolist() == model.group.tolist()
    # every channel in its bone's part: the root's rotations and translation apart, nothing "other"
    for c, g, p in zip(model.channels, model.group, b.parts):
        want = (0 if is_angle(c) else ROOT_POS) if p == "root" else GROUP_NAMES.index(p)
        assert g == want, (c, GROUP_NAMES[g], p)
    assert OTHER not in model.group
    # each joint group drops out of this naming's take, and the blend fills it (not only holds)
    for g in skelmap.GROUPS:
        obs, bursts = drop_mask(f"gaps:{g}", test, seed=1, require_erased=False)
        cols = b.mask(g)
        assert not (~obs[:, ~cols]).any()
        if not bursts:
            continue
        fill = _fill(model, test.frames, obs)
        miss = ~obs
        np.testing.assert_array_equal(fill[obs], test.frames[obs])
        assert not np.allclose(fill[miss], _hold(test.frames, obs)[miss]), g


def test_default_on_cmu_asf_keeps_its_groups_and_old_files_load_as_they_were(data, tmp_path, capsys):
    amc = data / "cmu" / "07" / "07_02.amc"
    out = tmp_path / "asf.npz"
    assert main(["train", "default-blend", str(amc), "-o", str(out), "-q"]) == 0
    model = modelfile.load_model(str(out))
    assert model.meta["skeleton_map"] == "cmu-asf"
    np.testing.assert_array_equal(model.group, legacy_groups(model.channels))  # the table it always had
    assert OTHER not in model.group
    take = read_motion(amc)
    b = skelmap.Binding.of(take.channels)
    assert (~drop_mask("gaps", take, seed=0)[0]).any()
    for g in skelmap.GROUPS:
        assert b.mask(g).any()  # SkeletonError were there none
        obs, bursts = drop_mask(f"gaps:{g}", take, seed=0, require_erased=False)
        assert (~obs).any() == bool(bursts) and not (~obs[:, ~b.mask(g)]).any()
    # a file written before groups were recorded (no 'group' array) loads with the old table
    for trained in (out, tmp_path / "bvh.npz"):
        if trained.name == "bvh.npz":
            converted(data, "08_02", "cmu-bvh", tmp_path / "t.bvh")
            assert main(["train", "default-blend", str(tmp_path / "t.bvh"), "-o", str(trained), "-q"]) == 0
        meta, arrays = modelfile.load_arrays(str(trained))
        old = tmp_path / f"old-{trained.name}"
        modelfile.save_arrays(str(old), {k: v for k, v in meta.items() if k != "skeleton_map"},
                              {k: v for k, v in arrays.items() if k != "group"})
        m_old = modelfile.load_model(str(old))
        np.testing.assert_array_equal(m_old.group, legacy_groups(m_old.channels))
    # ... which for a BVH model was "hold everything but the Hips", as before skeleton maps
    assert set(np.unique(m_old.group)) == {0, OTHER, ROOT_POS}
    capsys.readouterr()


def test_a_model_of_another_skeleton_is_a_clear_error(data, tmp_path, capsys):
    """Trained on CMU ASF, a CMU BVH take of the same recordings cannot be filled: its angles are
    another convention (rest pose, joint axes, order); --skeleton does not change that."""
    out = tmp_path / "asf.npz"
    assert main(["train", "default", str(data / "cmu" / "07" / "07_02.amc"), "-o", str(out), "-q"]) == 0
    take = data / "bvh" / "07_01.bvh"
    capsys.readouterr()
    for argv in (["replay", str(take), "--serve", str(out), "--drop", "gaps", "--skeleton", "cmu-bvh",
                  "--out", str(tmp_path / "f.bvh"), "-q"],
                 ["eval", "--protocol", "gaps", "--method", "default", "--model", str(out), "--test", str(take),
                  "--skeleton", "cmu-bvh", "-q"]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert err.startswith("lacuna: error:") and "cmu-asf" in err and "cmu-bvh" in err
    assert not (tmp_path / "f.bvh").exists()


def test_patterns_that_would_erase_nothing_name_the_skeleton_and_groups(data, tmp_path, capsys):
    """A take without arms (humanik naming): an arm drop is an error naming the skeleton and the
    bones looked for, in the replay's drop, in eval's gaps and in default's calibration."""
    full = converted(data, "08_02", "humanik", tmp_path / "full.bvh")
    hier = full.skeleton
    drop = {i for i, j in enumerate(hier.joints) if "Shoulder" in j.name}
    changed = True
    while changed:
        changed = False
        for i, j in enumerate(hier.joints):
            if i not in drop and j.parent in drop:
                drop.add(i)
                changed = True
    idx = {i: k for k, i in enumerate(i for i in range(len(hier.joints)) if i not in drop)}
    joints = [Joint(j.name, j.kind, j.offset, j.channels, None if j.parent is None else idx[j.parent])
              for i, j in enumerate(hier.joints) if i not in drop]
    h2 = Hierarchy(joints)
    m = Motion(full.frames[:, full.index(h2.channels)], h2.channels, full.fps, h2, "noarms.bvh")
    write_bvh(tmp_path / "noarms.bvh", m)
    take = str(tmp_path / "noarms.bvh")
    assert main(["train", "default", take, "-o", str(tmp_path / "m.npz"), "-q"]) == 0
    capsys.readouterr()
    cases = [["replay", take, "--serve", str(tmp_path / "m.npz"), "--drop", "gaps:left-arm,right-arm", "-q"],
             ["train", "default-blend", take, "-o", str(tmp_path / "c.npz"), "--calibrate", take, "--skeleton",
              str(_arms_only_map(tmp_path))]]
    for argv in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert err.startswith("lacuna: error:") and "skeleton" in err and "left-arm" in err, err


def _arms_only_map(tmp_path):
    """A map that knows only the (absent) arms and the root: calibration would erase nothing."""
    p = tmp_path / "armsonly.toml"
    p.write_text('name = "arms-only"\nformat = "bvh"\n[root]\nbone = "Hips"\n[bones]\n'
                 'Hips = { part = "root" }\nLeftArm = { part = "left-arm" }\nRightArm = { part = "right-arm" }\n')
    return p


def test_trained_on_bvh_default_beats_hold_in_eval_and_through_the_daemon(data, tmp_path, capsys):
    """Trained on CMU's BVH 08_02 and 09_11, scored on the held-out BVH 07_01 (a papers' test
    take, used here only to score) over the gaps protocol's seeds 0-4: in ``lacuna eval`` and
    through one real daemon process (``lacuna replay --connect``, one replay per seed)."""
    bvh = data / "bvh"
    js = tmp_path / "e.json"
    train = ["--train", str(bvh / "08_02.bvh"), "--train", str(bvh / "09_11.bvh")]
    rms = {}
    for method in ("default", "hold"):
        assert main(["eval", "--protocol", "gaps", "--method", method, *train, "--test", str(bvh / "07_01.bvh"),
                     "--seeds", "0-4", "--json", str(js), "-q"]) == 0
        rows = {r["metric"]: r for r in json.loads(js.read_text())["results"] if r["test"] == "07_01"}
        assert rows["rms_deg"]["n"] > 10000
        rms[method] = rows["rms_deg"]["value"]
    assert rms["default"] < 0.9 * rms["hold"], rms
    model = tmp_path / "bvh.npz"
    assert main(["train", "default", str(bvh / "08_02.bvh"), str(bvh / "09_11.bvh"), "-o", str(model), "-q"]) == 0
    se = sh = n = 0.0
    with DaemonProcess({"model": str(model)}, workdir=str(tmp_path / "d")) as d:
        for seed in range(5):
            r = tmp_path / f"r{seed}.json"
            assert main(["replay", str(bvh / "07_01.bvh"), "--connect", d.endpoint, "--drop", "gaps", "--seed",
                         str(seed), "--speed", "0", "--stream", f"s{seed}", "--out", str(tmp_path / f"f{seed}.bvh"),
                         "--json", str(r), "-q"]) == 0
            acc = json.loads(r.read_text())["accuracy"]
            k = acc["erased_angle_values"]
            assert k > 1000 and acc["hold_rms_deg"] is not None
            se += acc["rms_deg"] ** 2 * k
            sh += acc["hold_rms_deg"] ** 2 * k
            n += k
    assert np.sqrt(se / n) < 0.9 * np.sqrt(sh / n), (np.sqrt(se / n), np.sqrt(sh / n))
    capsys.readouterr()


def test_a_channel_that_wraps_at_180_fills_as_if_it_did_not(data, tmp_path):
    """Euler angles wrap: a BVH joint whose rest sits near +-180 degrees (another rotation order or
    rest pose) must fill as one that does not.  The limbs' channels of CMU's BVH 08_02 (training)
    and 07_01 (filled) are turned so that each one's mean is at 180 degrees and its values cross
    +-180 all the time; the errors of the fill are the same as on the original takes."""
    from blend.train import train_model
    from mocap.protocols import Gaps

    train = converted(data, "08_02", "cmu-bvh", tmp_path / "a.bvh")
    test = converted(data, "07_01", "cmu-bvh", tmp_path / "b.bvh")
    ang = np.array([is_angle(c) for c in test.channels])
    limbs = ang & ~np.array([c.startswith("Hips.") for c in test.channels])

    shift = np.where(limbs, 180.0 - circular_mean_deg(train.frames), 0.0)

    def turned(x):
        return np.where(limbs, wrap180(x + shift), x)

    assert (np.abs(turned(test.frames)[:, limbs]) > 170).mean() > 0.2  # most channels cross +-180
    errs = []
    for a, b in ((train.frames, test.frames), (turned(train.frames), turned(test.frames))):
        model = train_model([a], train.channels, ["08_02"])
        obs, _ = Gaps(0).occlusion("07_01", test.n_frames, test.channels, test.fps)
        errs.append(wrap180(_fill(model, b, obs) - b)[~obs & ang[None]])
    assert errs[0].size > 1000
    np.testing.assert_allclose(errs[1], errs[0], atol=1e-6)


def test_bones_no_map_knows_train_with_a_warning_that_default_only_holds(tmp_path, capsys):
    t = np.arange(240)
    rows = ["# fps=120", "frame,knee.rx,knee.ry,elbow.rx"] + [
        f"{k},{10 * np.sin(k / 10):.4f},{5 * np.cos(k / 7):.4f},{3 * np.sin(k / 5):.4f}" for k in t]
    (tmp_path / "odd.csv").write_text("\n".join(rows) + "\n")
    assert main(["train", "default-blend", str(tmp_path / "odd.csv"), "-o", str(tmp_path / "m.npz")]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "match no known skeleton" in err and "hold the last value" in err
    model = modelfile.load_model(str(tmp_path / "m.npz"))
    assert set(model.group.tolist()) == {OTHER} and model.meta["skeleton_map"] == ""
    # `lacuna train default` (the blend mixed with the HLM) says the same of its blend
    assert main(["train", "default", str(tmp_path / "odd.csv"), "-o", str(tmp_path / "d.npz")]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "match no known skeleton" in err and "hold the last value" in err
