"""Motion as CSV: one row per frame, one column per named channel.

Layout (what ``write_csv`` produces and ``read_csv`` expects)::

    # fps=120
    # source=07_01.amc
    time,root.tx,root.ty,...,ltoes.rx
    0,8.87208,15.7511,...
    0.008333333333333333,...

* Comment lines (``#``) before the header carry ``key=value`` metadata; ``fps`` is the frame
  rate, the others land in ``Motion.meta``.
* The header names the channels (``bone.dof``).  A first column named ``time`` (seconds) is
  optional: without an ``fps`` line the rate is taken from it; with one, the two must agree.
* Values are written with full float precision, so a CSV round trip is exact.
* Empty cells (or ``nan``) are missing values: an error unless ``allow_missing=True``, then NaN.
"""
from __future__ import annotations

import csv
import io
import math
import os
import re

import numpy as np

from lacuna.errors import ParseError
from mocap.atomic import atomic_write_text
from mocap.motion import Motion

TIME_COLUMN = "time"
# A time column may wander from an even grid by this fraction of a frame period.
TIME_JITTER_FRAC = 0.1
# ... and may disagree with the fps line by this relative amount.
FPS_AGREE_REL = 1e-3
_META = re.compile(r"^\s*([A-Za-z_][\w.-]*)\s*[=:]\s*(.*?)\s*$")
_NAME = re.compile(r"^[^\s,\"']+$")


def parse_csv(text: str, path: str = "<csv>", fps: float | None = None, allow_missing: bool = False) -> Motion:
    """Parse CSV text into a Motion.

    Parameters
    ----------
    fps : frame rate to use when the file has neither an ``fps`` line nor a time column.
    allow_missing : read empty/``nan`` cells as NaN instead of failing.

    Returns
    -------
    Motion with ``frames`` (n_frames, n_channels), ``skeleton`` None.
    """
    lines = text.splitlines()
    meta: dict[str, str] = {}
    i = 0
    while i < len(lines) and (not lines[i].strip() or lines[i].lstrip().startswith("#")):
        body = lines[i].strip().lstrip("#")
        for item in body.split(";"):
            m = _META.match(item)
            if m:
                meta[m.group(1).lower()] = m.group(2)
        i += 1
    if i >= len(lines):
        raise ParseError(path, None, "no header line (expected channel names, e.g. 'time,root.tx,...')")
    header_line = i + 1
    header = [h.strip() for h in next(csv.reader([lines[i]]))]
    has_time = bool(header) and header[0].lower() == TIME_COLUMN
    names = header[1:] if has_time else header
    if not names:
        raise ParseError(path, header_line, "header names no channels")
    for k, n in enumerate(names):
        if n.lower() == TIME_COLUMN:
            raise ParseError(path, header_line, f"a {TIME_COLUMN!r} column must be the first column (found it in column {k + 1 + has_time})")
        if not n or not _NAME.match(n):
            raise ParseError(path, header_line, f"bad channel name {n!r} in column {k + 1 + has_time} of the header")
        try:
            float(n)
        except ValueError:
            pass
        else:
            raise ParseError(path, header_line, f"header expected (channel names), got numbers like {n!r}")
    seen: set[str] = set()
    for n in names:
        if n in seen:
            raise ParseError(path, header_line, f"channel {n!r} appears twice in the header")
        seen.add(n)

    width = len(header)
    rows: list[list[float]] = []
    row_lines: list[int] = []
    reader = csv.reader(io.StringIO("\n".join(lines[i + 1 :])))
    for cells in reader:
        lineno = header_line + reader.line_num
        if not cells or all(not c.strip() for c in cells):
            continue
        if cells[0].lstrip().startswith("#"):
            continue
        if len(cells) != width:
            raise ParseError(path, lineno, f"{len(cells)} values, the header has {width} columns")
        vals = []
        for k, c in enumerate(cells):
            c = c.strip()
            col = header[k]
            if not c or c.lower() == "nan":
                if allow_missing and not (has_time and k == 0):
                    vals.append(math.nan)
                    continue
                raise ParseError(path, lineno, f"column {col}: missing value {c!r}")
            try:
                v = float(c)
            except ValueError:
                raise ParseError(path, lineno, f"column {col}: not a number: {c!r}") from None
            if not math.isfinite(v):
                raise ParseError(path, lineno, f"column {col}: {c!r} is not finite")
            vals.append(v)
        rows.append(vals)
        row_lines.append(lineno)
    if not rows:
        raise ParseError(path, None, "no frames after the header")
    data = np.asarray(rows, dtype=np.float64)

    file_fps = None
    if "fps" in meta:
        try:
            file_fps = float(meta["fps"])
        except ValueError:
            file_fps = math.nan
        if not (math.isfinite(file_fps) and file_fps > 0):
            raise ParseError(path, None, f"fps={meta['fps']!r} in the header comments is not a positive number")
    if has_time:
        t = data[:, 0]
        data = data[:, 1:]
        if len(t) > 1:
            dt = np.diff(t)
            if (dt <= 0).any():
                k = int(np.flatnonzero(dt <= 0)[0]) + 1
                raise ParseError(path, row_lines[k], f"time {float(t[k])!r} does not increase (previous row {float(t[k - 1])!r})")
            period = 1.0 / file_fps if file_fps else float(np.median(dt))
            grid = t[0] + period * np.arange(len(t))
            off = np.abs(t - grid)
            if off.max() > TIME_JITTER_FRAC * period:
                k = int(np.argmax(off > TIME_JITTER_FRAC * period))
                raise ParseError(
                    path, row_lines[k],
                    f"time {float(t[k])!r} is off the frame grid (expected {float(grid[k])!r} for {1 / period:g} fps); "
                    "frames must be evenly spaced",
                )
            if file_fps is None:
                file_fps = 1.0 / period
                r = round(file_fps)
                if r > 0 and abs(file_fps - r) <= FPS_AGREE_REL * r:
                    file_fps = float(r)
        if t[0] != 0:
            meta["t0"] = repr(float(t[0]))
    if file_fps is None:
        file_fps = fps
    if file_fps is None:
        raise ParseError(path, None, "no frame rate: add a '# fps=120' line, a time column, or pass fps=")
    meta.pop("fps", None)
    return Motion(data, names, float(file_fps), None, path, dict(meta))


def read_csv(path: str | os.PathLike, fps: float | None = None, allow_missing: bool = False) -> Motion:
    """Read a CSV motion file (see ``parse_csv``)."""
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8-sig", errors="replace", newline="") as fh:
            text = fh.read()
    except OSError as e:
        raise ParseError(path, None, f"cannot read ({e.strerror or e})") from None
    return parse_csv(text, path, fps, allow_missing)


def _num(x: float) -> str:
    # repr is the shortest text that parses back to the same double: exact round trips.
    if math.isnan(x):
        return ""
    return repr(float(x)) if x != 0 else "0"


def format_csv(motion: Motion, time: bool = True) -> str:
    """CSV text for a motion; NaN (missing) values are written as empty cells."""
    if not math.isfinite(motion.fps) or motion.fps <= 0:
        raise ValueError(f"cannot write CSV: fps {motion.fps} is not a positive number")
    if np.isinf(motion.frames).any():
        raise ValueError("cannot write CSV: the motion has infinite values")
    for n in motion.channels:
        if not _NAME.match(n) or (n.lower() == TIME_COLUMN):
            raise ValueError(f"cannot write CSV: channel name {n!r} is not a plain word")
    out = [f"# fps={_num(motion.fps)}"]
    if motion.source:
        out.append(f"# source={os.path.basename(motion.source)}")
    out.append(",".join(([TIME_COLUMN] if time else []) + list(motion.channels)))
    for t, row in enumerate(motion.frames):
        cells = [_num(v) for v in row]
        if time:
            cells.insert(0, _num(t / motion.fps))
        out.append(",".join(cells))
    return "\n".join(out) + "\n"


def write_csv(path: str | os.PathLike, motion: Motion, time: bool = True) -> None:
    """Write a CSV motion file atomically (see ``format_csv``)."""
    atomic_write_text(path, format_csv(motion, time))
