"""CSV motion files: header, fps line, time column, errors on literal text, round trips."""
from __future__ import annotations

import numpy as np
import pytest

from lacuna.errors import ParseError
from mocap.csvio import format_csv, parse_csv, read_csv, write_csv
from mocap.io import read_motion, write_motion
from mocap.motion import Motion

CSV = """\
# fps=30
# source=take.amc
time,root.tx,lfemur.rx
0,1.5,10
0.03333333333333333,1.25,-20
0.06666666666666667,1,30.125
"""


def test_literal_csv():
    m = parse_csv(CSV, "t.csv")
    assert m.channels == ["root.tx", "lfemur.rx"] and m.fps == 30.0
    np.testing.assert_array_equal(m.frames, [[1.5, 10], [1.25, -20], [1, 30.125]])
    assert m.meta == {"source": "take.amc"}


def test_fps_from_time_column_alone():
    m = parse_csv(CSV.replace("# fps=30\n", ""))
    assert m.fps == 30.0


def test_fps_line_without_time_column():
    m = parse_csv("# fps=120\na.rx,b.rx\n1,2\n3,4\n")
    assert m.fps == 120.0 and m.frames.shape == (2, 2)


def test_fps_argument_when_the_file_has_none():
    assert parse_csv("a.rx\n1\n2\n", fps=60).fps == 60.0


def test_missing_values_allowed_on_request():
    m = parse_csv("# fps=30\na.rx,b.rx\n1,\n,nan\n", allow_missing=True)
    assert np.isnan(m.frames).tolist() == [[False, True], [True, True]]
    # and written back as empty cells
    back = parse_csv(format_csv(m), allow_missing=True)
    np.testing.assert_array_equal(back.frames, m.frames)


CSV_ERRORS = [
    # (name, text, line, fragment)
    ("empty", "", None, "no header line"),
    ("comments_only", "# fps=30\n\n", None, "no header line"),
    ("header_is_numbers", "# fps=30\n1,2\n3,4\n", 2, "header expected (channel names), got numbers like '1'"),
    ("empty_name", "# fps=30\na.rx,,b.rx\n1,2,3\n", 2, "bad channel name '' in column 2"),
    ("duplicate_name", "# fps=30\na.rx,b.rx,a.rx\n1,2,3\n", 2, "channel 'a.rx' appears twice"),
    ("time_only", "time\n0\n", 1, "header names no channels"),
    ("time_not_first", "a.rx,time\n1,0\n", 1, "a 'time' column must be the first column (found it in column 2)"),
    ("no_frames", "# fps=30\na.rx,b.rx\n\n", None, "no frames after the header"),
    ("too_few_values", CSV.replace("1.25,-20", "1.25"), 5, "2 values, the header has 3 columns"),
    ("too_many_values", CSV.replace("1,30.125", "1,30.125,7"), 6, "4 values, the header has 3 columns"),
    ("not_a_number", CSV.replace("-20", "-2O"), 5, "column lfemur.rx: not a number: '-2O'"),
    ("nan", CSV.replace("-20", "nan"), 5, "column lfemur.rx: missing value 'nan'"),
    ("empty_cell", CSV.replace("1.25,-20", ",-20"), 5, "column root.tx: missing value ''"),
    ("inf", CSV.replace("-20", "-inf"), 5, "column lfemur.rx: '-inf' is not finite"),
    ("bad_fps", CSV.replace("fps=30", "fps=fast"), None, "fps='fast' in the header comments is not a positive number"),
    ("zero_fps", CSV.replace("fps=30", "fps=0"), None, "fps='0'"),
    ("time_goes_back", CSV.replace("0.06666666666666667", "0.01"), 6, "time 0.01 does not increase"),
    ("time_off_grid", CSV.replace("0.06666666666666667", "0.09"), 6, "time 0.09 is off the frame grid (expected 0.0666"),
    ("time_disagrees_with_fps", CSV.replace("fps=30", "fps=60"), 5, "off the frame grid"),
    ("no_rate_at_all", "a.rx\n1\n2\n", None, "no frame rate: add a '# fps=120' line"),
]


@pytest.mark.parametrize("name,text,line,fragment", CSV_ERRORS, ids=[c[0] for c in CSV_ERRORS])
def test_raises_on_malformed_csv(name, text, line, fragment):
    with pytest.raises(ParseError) as ei:
        parse_csv(text, "bad.csv")
    e = ei.value
    assert e.path == "bad.csv" and e.line == line, str(e)
    assert fragment in str(e)


def test_round_trip_is_exact_with_and_without_time(tmp_path, rng):
    frames = rng.normal(scale=100.0, size=(50, 4))
    frames[3, 1] = 0.0
    frames[4, 2] = 1e-300
    m = Motion(frames, ["root.tx", "root.ry", "lfemur.rx", "ltibia.rx"], 120.0)
    for time in (True, False):
        p = tmp_path / f"m{time}.csv"
        write_csv(p, m, time=time)
        back = read_csv(p)
        assert back.channels == m.channels and back.fps == 120.0
        np.testing.assert_array_equal(back.frames, m.frames)


def test_odd_frame_rate_round_trips(tmp_path):
    m = Motion(np.arange(12.0).reshape(6, 2), ["a.rx", "b.rx"], 1 / 0.0083333)
    write_csv(tmp_path / "m.csv", m)
    assert read_csv(tmp_path / "m.csv").fps == m.fps


def test_csv_with_wrong_skeleton_is_refused(data, tmp_path):
    m = read_motion(data / "cmu" / "07" / "07_01.amc")
    write_motion(tmp_path / "upper.csv", m.select(m.channels[:20]))
    with pytest.raises(ParseError, match=r"channels do not match skeleton .*07.asf: missing 42 \(lowerback.rx, "):
        read_motion(tmp_path / "upper.csv", asf=data / "cmu" / "07" / "07.asf")
    with pytest.raises(ValueError, match="writing AMC needs an ASF skeleton"):
        write_motion(tmp_path / "upper.amc", read_motion(tmp_path / "upper.csv"))
    assert not (tmp_path / "upper.amc").exists()


def test_unknown_extension_is_named(tmp_path):
    with pytest.raises(ValueError, match=r"x.c3d: unknown motion format '.c3d' \(expected .amc, .bvh, .csv\)"):
        read_motion(tmp_path / "x.c3d")


def test_windows_line_endings_and_byte_order_mark(tmp_path):
    p = tmp_path / "crlf.csv"
    p.write_bytes(b"\xef\xbb\xbf" + CSV.replace("\n", "\r\n").encode())
    m = read_csv(p)
    np.testing.assert_array_equal(m.frames, parse_csv(CSV).frames)
    assert m.fps == 30.0
