"""ASF/AMC: errors on literal text (file and line named), and round trips of the real files."""
from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import pytest

from lacuna.errors import ParseError
from mocap.asf import format_amc, parse_amc, parse_asf, read_amc, write_amc
from mocap.io import read_motion, write_motion

ASF = """\
# a three-bone leg
:version 1.10
:name test
:units
  mass 1.0
  length 1.0
  angle deg
:root
   order TX TY TZ RX RY RZ
   axis XYZ
   position 0 0 0
   orientation 0 0 0
:bonedata
  begin
     id 1
     name lhipjoint
     direction 0 -1 0
     length 1
     axis 0 0 0 XYZ
  end
  begin
     id 2
     name lfemur
     direction 0 -1 0
     length 5
     axis 0 0 20 XYZ
    dof rx ry rz
    limits (-160.0 20.0)
           (-70.0 70.0)
           (-60.0 70.0)
  end
  begin
     id 3
     name ltibia
     direction 0 -1 0
     length 5
     axis 0 0 0 XYZ
    dof rx
    limits (-10 170)
  end
:hierarchy
  begin
    root lhipjoint
    lhipjoint lfemur
    lfemur ltibia
  end
"""

AMC = """\
#!OML:ASF test.asf
:FULLY-SPECIFIED
:DEGREES
1
root 1 2 3 4 5 6
lfemur 10 20 30
ltibia 40
2
ltibia 41
root 1.5 2 3 4 5 6
lfemur 11 21 31
"""


@pytest.fixture(scope="module")
def skel():
    return parse_asf(ASF, "test.asf")


def test_literal_amc_reads_bones_by_name(skel):
    m = parse_amc(AMC, skel, "t.amc")
    assert m.channels == ["root.tx", "root.ty", "root.tz", "root.rx", "root.ry", "root.rz",
                          "lfemur.rx", "lfemur.ry", "lfemur.rz", "ltibia.rx"]
    np.testing.assert_array_equal(m.frames, [[1, 2, 3, 4, 5, 6, 10, 20, 30, 40],
                                             [1.5, 2, 3, 4, 5, 6, 11, 21, 31, 41]])
    assert m.fps == 120.0
    assert m.meta["amc_bone_order"] == ["root", "lfemur", "ltibia"]


def test_radians_amc_is_converted_to_degrees(skel):
    m = parse_amc(AMC.replace(":DEGREES", ":RADIANS"), skel)
    assert m.frames[0, 0] == 1.0  # translation untouched
    assert m.frames[0, 6] == pytest.approx(np.degrees(10.0))


AMC_ERRORS = [
    # (name, text, line, fragment)
    ("truncated_mid_frame", AMC.split("lfemur 11")[0], 8, "file ends inside frame 2: no line for bone 'lfemur'"),
    ("truncated_mid_line", AMC.replace("lfemur 11 21 31\n", "lfemur 11 2"), 11, "lfemur needs 3 values (got 2"),
    ("too_many_values", AMC.replace("ltibia 40", "ltibia 40 41"), 7, "ltibia needs 1 values (got 2"),
    ("not_a_number", AMC.replace("lfemur 10 20 30", "lfemur 10 2O 30"), 6, "not a number in '10 2O 30'"),
    ("nan", AMC.replace("lfemur 10 20 30", "lfemur 10 nan 30"), 6, "NaN or infinity"),
    ("inf", AMC.replace("root 1 2 3", "root 1 -inf 3"), 5, "NaN or infinity"),
    ("unknown_bone", AMC.replace("ltibia 40", "rtibia 40"), 7, "bone 'rtibia' is not in skeleton test.asf"),
    ("bone_twice", AMC.replace("ltibia 41", "lfemur 1 2 3\nlfemur 1 2 3\nltibia 41"), 10, "bone lfemur appears twice in frame 2"),
    ("frame_lacks_bone", AMC.replace("ltibia 40\n", ""), 4, "frame 1 lacks bone 'ltibia'"),
    ("frame_number_skips", AMC.replace("\n2\n", "\n3\n"), 8, "frame number 3 follows frame 1 (expected 2)"),
    ("bone_before_frame", ":DEGREES\nroot 1 2 3 4 5 6\n", 2, "bone line before the first frame number"),
    ("empty", "", None, "no frames"),
    ("header_only", ":FULLY-SPECIFIED\n:DEGREES\n\n\n", None, "no frames"),
]


@pytest.mark.parametrize("name,text,line,fragment", AMC_ERRORS, ids=[c[0] for c in AMC_ERRORS])
def test_raises_on_malformed_amc(skel, name, text, line, fragment):
    with pytest.raises(ParseError) as ei:
        parse_amc(text, skel, "bad.amc")
    e = ei.value
    assert e.path == "bad.amc" and e.line == line, str(e)
    assert fragment in str(e)
    assert str(e).startswith(f"bad.amc:{line}: " if line else "bad.amc: ")


ASF_ERRORS = [
    ("unknown_dof", ASF.replace("dof rx\n", "dof rw\n"), 38, "bone ltibia: unknown dof 'rw'"),
    ("dof_twice", ASF.replace("dof rx ry rz", "dof rx ry rx"), 27, "bone lfemur: a dof appears twice in 'rx ry rx'"),
    ("root_order_twice", ASF.replace("order TX TY TZ", "order TX TY TX"), 9, "root order names a dof twice"),
    ("root_order_dof", ASF.replace("order TX TY", "order TX TQ"), 9, "root order has unknown dof 'tq'"),
    ("direction_count", ASF.replace("direction 0 -1 0\n     length 5\n     axis 0 0 20", "direction 0 -1\n     length 5\n     axis 0 0 20"), 24, "direction needs 3 numbers (got 2"),
    ("length_not_number", ASF.replace("length 5\n     axis 0 0 20", "length five\n     axis 0 0 20"), 25, "length: not a number"),
    ("limits_count", ASF.replace("           (-60.0 70.0)\n", ""), 30, "bone lfemur: 3 dofs but 2 limits"),
    ("bad_limit", ASF.replace("(-10 170)", "(-10 abc)"), 39, "bone ltibia: bad limit 'abc'"),
    ("truncated_in_bone", ASF.split("    dof rx\n")[0], 37, "bone ltibia not closed with 'end' (file truncated?)"),
    ("hierarchy_unknown_bone", ASF.replace("lfemur ltibia", "lfemur rtibia"), 45, "':hierarchy' names bone 'rtibia'"),
    ("unknown_attribute", ASF.replace("     length 1\n", "     lenght 1\n"), 18, "unknown bone attribute 'lenght'"),
    ("no_root", ASF.replace("   order TX TY TZ RX RY RZ\n", ""), None, "no ':root' section with an 'order' line"),
    ("duplicate_bone", ASF.replace("name ltibia", "name lfemur").replace("lfemur ltibia", "lfemur lfemur"), None, "bone name 'lfemur' appears twice"),
]


@pytest.mark.parametrize("name,text,line,fragment", ASF_ERRORS, ids=[c[0] for c in ASF_ERRORS])
def test_raises_on_malformed_asf(name, text, line, fragment):
    with pytest.raises(ParseError) as ei:
        parse_asf(text, "bad.asf")
    assert ei.value.line == line, str(ei.value)
    assert fragment in str(ei.value)


def test_writer_refuses_to_drop_or_invent_channels(skel):
    m = parse_amc(AMC, skel, "t.amc")
    with pytest.raises(ValueError, match=r"lacks 1 skeleton channels \(ltibia.rx\)"):
        format_amc(m.select(m.channels[:-1]), skel)
    m.frames[1, 7] = np.nan
    with pytest.raises(ValueError, match="frame 2 channel lfemur.ry is nan"):
        format_amc(m)


def test_missing_file_is_a_parse_error(tmp_path):
    with pytest.raises(ParseError, match="nothing.amc: cannot read"):
        read_amc(tmp_path / "nothing.amc", asf=parse_asf(ASF))
    with pytest.raises(ParseError, match="no ASF skeleton beside it"):
        read_amc(tmp_path / "nothing.amc")


def _amcs(data: Path, subject: str) -> list[Path]:
    files = sorted((data / "cmu" / subject).glob("*.amc"))
    assert files, f"no AMC files for subject {subject} in {data}"
    return files


@pytest.mark.parametrize("subject", ["07", "35"])
def test_every_real_amc_round_trips_exactly(data, tmp_path, subject):
    orders = set()
    for f in _amcs(data, subject):
        m = read_amc(f)
        assert m.frames.shape[1] == 62 and m.n_frames > 100
        assert np.isfinite(m.frames).all()
        out = tmp_path / f.name
        write_amc(out, m)
        back = read_amc(out, asf=m.skeleton)
        assert back.channels == m.channels
        np.testing.assert_array_equal(back.frames, m.frames, err_msg=f.name)
        # written in the bone order the file came in
        assert back.meta["amc_bone_order"] == m.meta["amc_bone_order"]
        orders.add(tuple(m.meta["amc_bone_order"]))
    if subject == "35":
        # CMU's original 35_01 and the rebuilt trials order bones differently: both were read.
        assert len(orders) == 2


def test_cmu_ordered_amc_written_in_skeleton_order_reads_back_equal(data, tmp_path):
    # CMU's own 35_01 orders bones root, lowerback, ...; the ASF (and the rebuilt trials) lfemur first.
    m = read_amc(data / "cmu" / "35" / "35_01.amc")
    skel_order = list(m.skeleton.dofs_by_bone())
    assert m.meta["amc_bone_order"] != skel_order
    out = tmp_path / "35_01.amc"
    write_amc(out, m, bone_order=skel_order)
    back = read_amc(out, asf=m.skeleton)
    assert back.meta["amc_bone_order"] == skel_order
    np.testing.assert_array_equal(back.frames, m.frames)


def test_shuffled_bone_lines_read_the_same(data, rng):
    """Reading is by bone name: any order of lines within a frame gives the same frames."""
    f = data / "cmu" / "07" / "07_01.amc"
    m = read_amc(f)
    lines = format_amc(m.slice(0, 5)).splitlines()
    out, block = [], []
    r = random.Random(int(rng.integers(1 << 30)))
    for ln in lines[2:] + ["END"]:
        if ln.isdigit() or ln == "END":
            r.shuffle(block)
            out += block
            block = []
            if ln != "END":
                out.append(ln)
        else:
            block.append(ln)
    back = parse_amc("\n".join(out), m.skeleton)
    np.testing.assert_array_equal(back.frames, m.frames[:5])


def test_amc_to_csv_to_amc(data, tmp_path):
    src = data / "cmu" / "07" / "07_01.amc"
    m = read_motion(src)
    write_motion(tmp_path / "07_01.csv", m)
    c = read_motion(tmp_path / "07_01.csv", asf=data / "cmu" / "07" / "07.asf")
    assert c.fps == 120.0 and c.channels == m.channels
    write_motion(tmp_path / "07_01.amc", c)
    back = read_motion(tmp_path / "07_01.amc", asf=data / "cmu" / "07" / "07.asf")
    np.testing.assert_array_equal(back.frames, m.frames)
    assert back.channels == m.channels


def test_windows_line_endings_and_byte_order_mark(skel, tmp_path):
    (tmp_path / "t.asf").write_bytes(b"\xef\xbb\xbf" + ASF.replace("\n", "\r\n").encode())
    (tmp_path / "t.amc").write_bytes(b"\xef\xbb\xbf" + AMC.replace("\n", "\r\n").encode())
    m = read_amc(tmp_path / "t.amc")
    np.testing.assert_array_equal(m.frames, parse_amc(AMC, skel).frames)
