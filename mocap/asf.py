"""ASF skeletons and AMC motions (Acclaim format, as used by the CMU database).

Channels are named ``bone.dof`` and ordered as the ASF declares them: the root's ``order``
first, then every bone with dofs in ``:bonedata`` order.  AMC lines are read *by bone name*:
CMU's own files and the rebuilt subject-35 files order bones differently within a frame.

References
----------
Acclaim ASF/AMC file format, as documented with the CMU Graphics Lab Motion Capture Database.
"""
from __future__ import annotations

import glob
import io
import math
import os
from dataclasses import dataclass, field

import numpy as np

from lacuna.errors import ParseError
from mocap.atomic import atomic_write_text
from mocap.motion import Motion

AMC_FPS = 120.0
_VALID_DOFS = ("tx", "ty", "tz", "rx", "ry", "rz", "l")


@dataclass
class Bone:
    name: str
    dofs: list[str]
    direction: tuple[float, float, float] = (0.0, 0.0, 0.0)
    length: float = 0.0
    axis: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis_order: str = "XYZ"
    limits: list[tuple[float, float]] = field(default_factory=list)


@dataclass
class Skeleton:
    """An ASF skeleton: root dofs, bones in file order, the hierarchy, and the raw text."""

    name: str
    root_order: list[str]
    root_axis: str
    bones: list[Bone]
    hierarchy: dict[str, list[str]]
    units: dict[str, str]
    source: str = ""
    text: str = ""

    @property
    def channels(self) -> list[str]:
        out = [f"root.{d}" for d in self.root_order]
        for b in self.bones:
            out += [f"{b.name}.{d}" for d in b.dofs]
        return out

    def dofs_by_bone(self) -> dict[str, list[str]]:
        d = {"root": list(self.root_order)}
        for b in self.bones:
            if b.dofs:
                d[b.name] = list(b.dofs)
        return d


def _floats(path: str, lineno: int, parts: list[str], n: int | None, what: str) -> list[float]:
    if n is not None and len(parts) != n:
        raise ParseError(path, lineno, f"{what} needs {n} numbers (got {len(parts)}: {' '.join(parts)!r})")
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise ParseError(path, lineno, f"{what}: not a number in {' '.join(parts)!r}") from None
    return vals


def parse_asf(text: str, path: str = "<asf>") -> Skeleton:
    """Parse ASF text.  Raises ParseError naming the file and line."""
    lines = text.splitlines()
    section = None
    name = ""
    units: dict[str, str] = {}
    root_order: list[str] = []
    root_axis = "XYZ"
    bones: list[Bone] = []
    hierarchy: dict[str, list[str]] = {}
    cur: Bone | None = None
    in_limits = False
    hier_lines: list[tuple[int, str]] = []
    for i, raw in enumerate(lines, 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        if line.startswith(":"):
            parts = line.split()
            key = parts[0][1:].lower()
            section = key
            in_limits = False
            if key == "name" and len(parts) > 1:
                name = parts[1]
            continue
        parts = line.split()
        key = parts[0].lower()
        if section == "units":
            if len(parts) >= 2:
                units[key] = parts[1]
        elif section == "root":
            if key == "order":
                root_order = [p.lower() for p in parts[1:]]
                bad = [p for p in root_order if p not in _VALID_DOFS]
                if bad:
                    raise ParseError(path, i, f"root order has unknown dof {bad[0]!r}")
                if len(set(root_order)) != len(root_order):
                    raise ParseError(path, i, f"root order names a dof twice: {' '.join(parts[1:])}")
            elif key == "axis" and len(parts) > 1:
                root_axis = parts[1].upper()
        elif section == "bonedata":
            if key == "begin":
                cur = Bone(name="", dofs=[])
                in_limits = False
            elif key == "end":
                if cur is None:
                    raise ParseError(path, i, "'end' without 'begin'")
                if not cur.name:
                    raise ParseError(path, i, "bone without a name")
                if cur.dofs and cur.limits and len(cur.limits) != len(cur.dofs):
                    raise ParseError(path, i, f"bone {cur.name}: {len(cur.dofs)} dofs but {len(cur.limits)} limits")
                bones.append(cur)
                cur = None
                in_limits = False
            elif cur is None:
                raise ParseError(path, i, f"{parts[0]!r} outside a begin/end block")
            elif key == "name":
                if len(parts) != 2:
                    raise ParseError(path, i, "bone name must be one word")
                cur.name = parts[1]
            elif key == "direction":
                cur.direction = tuple(_floats(path, i, parts[1:], 3, "direction"))  # type: ignore[assignment]
            elif key == "length":
                cur.length = _floats(path, i, parts[1:], 1, "length")[0]
            elif key == "axis":
                cur.axis = tuple(_floats(path, i, parts[1:4], 3, "axis"))  # type: ignore[assignment]
                cur.axis_order = parts[4].upper() if len(parts) > 4 else "XYZ"
            elif key == "dof":
                cur.dofs = [p.lower() for p in parts[1:]]
                bad = [p for p in cur.dofs if p not in _VALID_DOFS]
                if bad:
                    raise ParseError(path, i, f"bone {cur.name}: unknown dof {bad[0]!r}")
                if len(set(cur.dofs)) != len(cur.dofs):
                    raise ParseError(path, i, f"bone {cur.name}: a dof appears twice in {' '.join(parts[1:])!r}")
            elif key == "limits" or in_limits:
                in_limits = True
                body = line[len("limits"):] if key == "limits" else line
                body = body.replace("(", " ").replace(")", " ").split()
                vals = []
                for p in body:
                    try:
                        vals.append(float(p))
                    except ValueError:
                        raise ParseError(path, i, f"bone {cur.name}: bad limit {p!r}") from None
                if len(vals) != 2:
                    raise ParseError(path, i, f"bone {cur.name}: a limit is a pair (min max)")
                cur.limits.append((vals[0], vals[1]))
            elif key == "id" or key == "bodymass" or key == "cofmass":
                pass
            else:
                raise ParseError(path, i, f"unknown bone attribute {parts[0]!r}")
        elif section == "hierarchy":
            if key in ("begin", "end"):
                continue
            hierarchy.setdefault(parts[0], []).extend(parts[1:])
            hier_lines.extend((i, n) for n in parts)
    if cur is not None:
        raise ParseError(path, len(lines), f"bone {cur.name or '?'} not closed with 'end' (file truncated?)")
    if not root_order:
        raise ParseError(path, None, "no ':root' section with an 'order' line")
    if not bones:
        raise ParseError(path, None, "no bones in ':bonedata'")
    seen = set()
    for b in bones:
        if b.name in seen or b.name == "root":
            raise ParseError(path, None, f"bone name {b.name!r} appears twice")
        seen.add(b.name)
    for i, n in hier_lines:
        if n != "root" and n not in seen:
            raise ParseError(path, i, f"':hierarchy' names bone {n!r}, which ':bonedata' does not define")
    return Skeleton(name, root_order, root_axis, bones, hierarchy, units, path, text)


def read_asf(path: str | os.PathLike) -> Skeleton:
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as fh:
            text = fh.read()
    except OSError as e:
        raise ParseError(path, None, f"cannot read ({e.strerror or e})") from None
    return parse_asf(text, path)


def find_asf(amc_path: str | os.PathLike) -> str:
    """CMU's layout: ``subjects/07/07_01.amc`` beside ``subjects/07/07.asf``."""
    amc_path = os.fspath(amc_path)
    d = os.path.dirname(os.path.abspath(amc_path))
    stem = os.path.basename(amc_path).split(".")[0]
    subj = stem.split("_")[0]
    for cand in (os.path.join(d, f"{subj}.asf"), os.path.join(d, f"{stem}.asf")):
        if os.path.exists(cand):
            return cand
    found = sorted(glob.glob(os.path.join(d, "*.asf")))
    if len(found) == 1:
        return found[0]
    raise ParseError(amc_path, None, f"no ASF skeleton beside it (looked for {subj}.asf in {d}); pass --asf")


def parse_amc(text: str, skeleton: Skeleton, path: str = "<amc>", fps: float = AMC_FPS) -> Motion:
    """Parse AMC text against a skeleton; bone lines are matched by name, in any order.

    Returns a Motion with ``frames`` of shape (n_frames, n_channels) in ``skeleton.channels``
    order, in degrees (a ``:RADIANS`` file, or an ASF with ``angle rad``, is converted).  The bone
    order of the first frame is kept in ``meta["amc_bone_order"]`` so a writer can reproduce it.
    Frame numbers must count up by one.  Raises ParseError naming the file and line.
    """
    dofs = skeleton.dofs_by_bone()
    channels = skeleton.channels
    col0: dict[str, int] = {}
    c = 0
    for b, ds in dofs.items():
        col0[b] = c
        c += len(ds)
    n_ch = len(channels)
    dofless = {b.name for b in skeleton.bones} - set(dofs)
    radians = skeleton.units.get("angle", "deg").lower().startswith("rad")
    rows: list[np.ndarray] = []
    cur: np.ndarray | None = None
    seen: list[str] = []
    first_order: list[str] = []
    cur_line = 0
    frame_no = 0

    def close(at_eof: bool) -> None:
        missing = [b for b in dofs if b not in seen]
        if missing:
            more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
            if at_eof:
                raise ParseError(path, cur_line, f"file ends inside frame {frame_no}: no line for bone {missing[0]!r}{more} (truncated?)")
            raise ParseError(path, cur_line, f"frame {frame_no} lacks bone {missing[0]!r}{more}")
        if not first_order:
            first_order.extend(seen)
        rows.append(cur)  # type: ignore[arg-type]

    for i, raw in enumerate(io.StringIO(text), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        if line.startswith(":"):
            key = line.split()[0].upper()
            if key == ":RADIANS":
                radians = True
            elif key == ":DEGREES":
                radians = False
            continue
        parts = line.split()
        if len(parts) == 1 and parts[0].isdigit():
            n = int(parts[0])
            if cur is not None:
                close(False)
                if n != frame_no + 1:
                    raise ParseError(path, i, f"frame number {n} follows frame {frame_no} (expected {frame_no + 1})")
            cur = np.full(n_ch, np.nan)
            seen = []
            cur_line = i
            frame_no = n
            continue
        if cur is None:
            raise ParseError(path, i, f"bone line before the first frame number: {line[:40]!r}")
        bone = parts[0]
        if bone not in dofs:
            if bone in dofless and len(parts) == 1:
                continue  # a bone with no dofs; tolerate an empty line for it
            raise ParseError(path, i, f"bone {bone!r} is not in skeleton {skeleton.source or skeleton.name}")
        want = len(dofs[bone])
        vals = parts[1:]
        if len(vals) != want:
            raise ParseError(path, i, f"bone {bone} needs {want} values (got {len(vals)}: {' '.join(vals)!r})")
        try:
            v = [float(x) for x in vals]
        except ValueError:
            raise ParseError(path, i, f"bone {bone}: not a number in {' '.join(vals)!r}") from None
        if not all(math.isfinite(x) for x in v):
            raise ParseError(path, i, f"bone {bone}: NaN or infinity in {' '.join(vals)!r}")
        if bone in seen:
            raise ParseError(path, i, f"bone {bone} appears twice in frame {frame_no}")
        seen.append(bone)
        cur[col0[bone] : col0[bone] + want] = v
    if cur is not None:
        close(True)
    if not rows:
        raise ParseError(path, None, "no frames (empty or not an AMC file)")
    frames = np.vstack(rows)
    if radians:
        rot = [j for j, ch in enumerate(channels) if ch.split(".")[-1].startswith("r")]
        frames[:, rot] = np.degrees(frames[:, rot])
    return Motion(frames, channels, fps, skeleton, path, {"amc_bone_order": first_order})


def read_amc(path: str | os.PathLike, asf: str | os.PathLike | Skeleton | None = None, fps: float = AMC_FPS) -> Motion:
    """Read an AMC file; its ASF is found beside it (CMU layout) unless given."""
    path = os.fspath(path)
    if isinstance(asf, Skeleton):
        skel = asf
    else:
        skel = read_asf(asf if asf is not None else find_asf(path))
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as fh:
            text = fh.read()
    except OSError as e:
        raise ParseError(path, None, f"cannot read ({e.strerror or e})") from None
    return parse_amc(text, skel, path, fps)


def _fmt(x: float) -> str:
    # repr is the shortest text that parses back to the same double: exact round trips.
    return repr(float(x)) if x != 0 else "0"


def format_amc(motion: Motion, skeleton: Skeleton | None = None, bone_order: list[str] | None = None) -> str:
    """AMC text (degrees, full float precision: it round trips exactly).

    Bones are written in ``bone_order``, else the order the motion was read in
    (``meta["amc_bone_order"]``), else the skeleton's order.  The motion must carry exactly the
    skeleton's channels (any order) with finite values: nothing is silently dropped.
    """
    skel = skeleton or motion.skeleton
    if not isinstance(skel, Skeleton):
        raise ValueError(f"writing AMC needs an ASF skeleton ({motion.source or 'this motion'} has none; pass asf=/--asf)")  # noqa: TRY004 (a user-facing error the CLI prints as one line)
    want = skel.channels
    have = set(motion.channels)
    missing = [ch for ch in want if ch not in have]
    extra = [ch for ch in motion.channels if ch not in set(want)]
    if missing or extra:
        what = []
        if missing:
            what.append(f"lacks {len(missing)} skeleton channels ({', '.join(missing[:4])}{' ...' if len(missing) > 4 else ''})")
        if extra:
            what.append(f"has {len(extra)} channels not in the skeleton ({', '.join(extra[:4])}{' ...' if len(extra) > 4 else ''})")
        raise ValueError(f"cannot write {motion.source or 'motion'} as AMC of skeleton {skel.source or skel.name}: it " + " and ".join(what))
    frames = motion.frames[:, motion.index(want)]
    bad = np.argwhere(~np.isfinite(frames))
    if len(bad):
        t, j = bad[0]
        raise ValueError(f"cannot write AMC: frame {t + 1} channel {want[j]} is {frames[t, j]} (fill gaps first)")
    dofs = skel.dofs_by_bone()
    col0: dict[str, int] = {}
    c = 0
    for b, ds in dofs.items():
        col0[b] = c
        c += len(ds)
    order = bone_order or motion.meta.get("amc_bone_order") or []
    if sorted(order) != sorted(dofs):
        order = list(dofs)
    out = [":FULLY-SPECIFIED", ":DEGREES"]
    for t in range(frames.shape[0]):
        row = frames[t]
        out.append(str(t + 1))
        for b in order:
            vals = row[col0[b] : col0[b] + len(dofs[b])]
            out.append(b + " " + " ".join(_fmt(v) for v in vals))
    return "\n".join(out) + "\n"


def write_amc(path: str | os.PathLike, motion: Motion, skeleton: Skeleton | None = None, bone_order: list[str] | None = None) -> None:
    """Write an AMC file atomically (see ``format_amc``)."""
    atomic_write_text(path, format_amc(motion, skeleton, bone_order))


def write_asf(path: str | os.PathLike, skeleton: Skeleton) -> None:
    """Write the skeleton back out (verbatim text when it was read from a file)."""
    if not skeleton.text:
        raise ValueError("this skeleton was not read from a file; nothing to write")
    atomic_write_text(path, skeleton.text)
