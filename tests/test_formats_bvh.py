"""BVH: reading, errors on literal text (file and line named), round trips of the real files."""
from __future__ import annotations

import numpy as np
import pytest

from lacuna.errors import ParseError
from mocap.bvh import format_bvh, parse_bvh, read_bvh, write_bvh
from mocap.io import read_motion, write_motion

BVH = """\
HIERARCHY
ROOT Hips
{
\tOFFSET 0 0 0
\tCHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
\tJOINT LeftUpLeg
\t{
\t\tOFFSET 1 0 0
\t\tCHANNELS 3 Zrotation Yrotation Xrotation
\t\tEnd Site
\t\t{
\t\t\tOFFSET 0 -2 0
\t\t}
\t}
}
MOTION
Frames: 2
Frame Time: 0.0333333
0 1 2 3 4 5 6 7 8
0.5 1 2 3 4 5 6 7 8.5
"""


def test_literal_bvh_channels_fps_and_hierarchy():
    m = parse_bvh(BVH, "t.bvh")
    assert m.channels == ["Hips.tx", "Hips.ty", "Hips.tz", "Hips.rz", "Hips.ry", "Hips.rx",
                          "LeftUpLeg.rz", "LeftUpLeg.ry", "LeftUpLeg.rx"]
    np.testing.assert_array_equal(m.frames, [[0, 1, 2, 3, 4, 5, 6, 7, 8], [0.5, 1, 2, 3, 4, 5, 6, 7, 8.5]])
    assert m.fps == 30.0 and m.meta["frame_time"] == 0.0333333
    h = m.skeleton
    assert [(j.name, j.kind, j.parent) for j in h.joints] == [
        ("Hips", "ROOT", None), ("LeftUpLeg", "JOINT", 0), ("LeftUpLeg_End", "End Site", 1)]
    assert h.joints[1].offset == (1.0, 0.0, 0.0) and h.joints[2].offset == (0.0, -2.0, 0.0)


def test_frame_rate_not_near_a_whole_number_is_kept():
    m = parse_bvh(BVH.replace("0.0333333", "0.007"))
    assert m.fps == pytest.approx(1 / 0.007)


def test_trailing_blank_lines_are_fine():
    m = parse_bvh(BVH + "\n\n   \n")
    assert m.n_frames == 2


BVH_ERRORS = [
    # (name, text, line, fragment)
    ("empty", "", None, "empty file"),
    ("bad_header", BVH.replace("HIERARCHY", "HIERACHY"), 1, "not a BVH file: expected 'HIERARCHY', got 'HIERACHY'"),
    ("no_root", "HIERARCHY\nMOTION\nFrames: 0\nFrame Time: 0.01\n", 1, "HIERARCHY has no ROOT"),
    ("missing_brace", BVH.replace("ROOT Hips\n{\n", "ROOT Hips\n"), 3, "expected '{', got 'OFFSET'"),
    ("offset_not_number", BVH.replace("OFFSET 1 0 0", "OFFSET 1 a 0"), 8, "OFFSET of LeftUpLeg: not a number: 'a'"),
    ("offset_nan", BVH.replace("OFFSET 1 0 0", "OFFSET 1 nan 0"), 8, "OFFSET of LeftUpLeg: 'nan' is not finite"),
    ("unknown_channel", BVH.replace("3 Zrotation Yrotation", "3 Wrotation Yrotation"), 9, "LeftUpLeg: unknown channel 'Wrotation'"),
    ("channel_count_word", BVH.replace("CHANNELS 3", "CHANNELS three"), 9, "count 'three' is not a whole number"),
    ("channel_count_short", BVH.replace("CHANNELS 3", "CHANNELS 4"), 10, "LeftUpLeg: unknown channel 'End'"),
    ("channel_twice", BVH.replace("3 Zrotation Yrotation Xrotation", "3 Zrotation Zrotation Xrotation"), 9, "channel Zrotation listed twice"),
    ("junk_in_joint", BVH.replace("\tJOINT LeftUpLeg", "\tJOINTT LeftUpLeg"), 6, "in Hips: expected JOINT, End Site or '}', got 'JOINTT'"),
    ("duplicate_joint", BVH.replace("JOINT LeftUpLeg", "JOINT Hips"), None, "joint name 'Hips' appears twice"),
    ("hierarchy_truncated", "\n".join(BVH.splitlines()[:9]) + "\n", 9, "hierarchy ends where '}' closing LeftUpLeg was expected (truncated?)"),
    ("motion_missing", BVH.split("MOTION")[0], 15, "no MOTION section"),
    ("frames_line_missing", BVH.split("Frames:")[0], 16, "file ends before the 'Frames:' line"),
    ("frames_not_int", BVH.replace("Frames: 2", "Frames: two"), 17, "Frames: 'two' is not a whole number"),
    ("frame_time_missing", BVH.replace("Frame Time: 0.0333333\n", ""), 18, "expected 'Frame Time: ...', got '0 1 2"),
    ("frame_time_zero", BVH.replace("0.0333333", "0"), 18, "Frame Time: 0 must be a positive number"),
    ("frame_time_word", BVH.replace("0.0333333", "fast"), 18, "Frame Time: 'fast' is not a number"),
    ("fewer_frames", BVH.replace("0.5 1 2 3 4 5 6 7 8.5\n", ""), 17, "Frames: 2 but 1 frame lines arrived (truncated?)"),
    ("more_frames", BVH + "1 1 2 3 4 5 6 7 8\n", 17, "Frames: 2 but 3 frame lines arrived"),
    ("wrong_value_count", BVH.replace("7 8.5", "7"), 20, "frame 1 has 8 values, the hierarchy has 9 channels"),
    ("truncated_last_line", BVH[: BVH.rindex("6 7 8.5")], 20, "frame 1 has 6 values"),
    ("not_a_number", BVH.replace("0 1 2 3", "0 1 x 3"), 19, "frame 0: not a number: 'x'"),
    ("nan_value", BVH.replace("7 8.5", "nan 8.5"), 20, "frame 1: channel LeftUpLeg.ry is 'nan' (NaN/inf)"),
    ("inf_value", BVH.replace("0 1 2 3", "inf 1 2 3"), 19, "frame 0: channel Hips.tx is 'inf'"),
]


@pytest.mark.parametrize("name,text,line,fragment", BVH_ERRORS, ids=[c[0] for c in BVH_ERRORS])
def test_raises_on_malformed_bvh(name, text, line, fragment):
    with pytest.raises(ParseError) as ei:
        parse_bvh(text, "bad.bvh")
    e = ei.value
    assert e.path == "bad.bvh" and e.line == line, str(e)
    assert fragment in str(e)


def test_writer_refuses_a_motion_without_hierarchy_or_with_gaps():
    m = parse_bvh(BVH)
    m.frames[1, 3] = np.nan
    with pytest.raises(ValueError, match="frame 1 channel Hips.rz is nan"):
        format_bvh(m)
    with pytest.raises(ValueError, match="needs a BVH hierarchy"):
        format_bvh(m.select(m.channels))


def test_literal_round_trip_in_another_column_order():
    m = parse_bvh(BVH)
    shuffled = m.select(m.channels[::-1])
    shuffled.skeleton = m.skeleton
    back = parse_bvh(format_bvh(shuffled))
    assert back.channels == m.channels
    np.testing.assert_array_equal(back.frames, m.frames)


@pytest.mark.parametrize("name", ["07_01", "08_02", "09_11"])
def test_real_bvh_round_trips_exactly(data, tmp_path, name):
    src = data / "bvh" / f"{name}.bvh"
    m = read_bvh(src)
    header_frames = int(next(ln for ln in src.read_text().splitlines() if ln.startswith("Frames:")).split()[1])
    # frame 0 (CMU's T-pose) is an ordinary frame
    assert m.n_frames == header_frames and m.frames.shape[1] == 96
    assert m.fps == 120.0 and m.meta["frame_time"] == 0.0083333
    assert m.channels[:6] == ["Hips.tx", "Hips.ty", "Hips.tz", "Hips.rz", "Hips.ry", "Hips.rx"]
    out = tmp_path / f"{name}.bvh"
    write_motion(out, m)
    back = read_motion(out)
    assert back.channels == m.channels
    np.testing.assert_array_equal(back.frames, m.frames)
    assert back.meta["frame_time"] == m.meta["frame_time"]
    assert [(j.name, j.kind, j.offset, j.channels, j.parent) for j in back.skeleton.joints] == \
        [(j.name, j.kind, j.offset, j.channels, j.parent) for j in m.skeleton.joints]
    # writing what was read back gives the same text
    write_bvh(tmp_path / "again.bvh", back)
    assert (tmp_path / "again.bvh").read_text() == out.read_text()


def test_bvh_to_csv_to_values(data, tmp_path):
    m = read_bvh(data / "bvh" / "09_11.bvh")
    write_motion(tmp_path / "09_11.csv", m)
    c = read_motion(tmp_path / "09_11.csv")
    assert c.channels == m.channels and c.fps == m.fps
    np.testing.assert_array_equal(c.frames, m.frames)


def test_windows_line_endings_and_byte_order_mark(tmp_path):
    p = tmp_path / "crlf.bvh"
    p.write_bytes(b"\xef\xbb\xbf" + BVH.replace("\n", "\r\n").encode())
    m = read_bvh(p)
    np.testing.assert_array_equal(m.frames, parse_bvh(BVH).frames)
