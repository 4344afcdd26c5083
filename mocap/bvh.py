"""BVH (Biovision hierarchy) motion files: reader and writer.

Channels are named ``Joint.dof``: ``Xrotation`` -> ``Joint.rx``, ``Yposition`` -> ``Joint.ty``,
in file order (joint by joint, each joint's channels in its ``CHANNELS`` order), so a frame row
of the file is a row of ``Motion.frames``.  The hierarchy (offsets, channel lists, End Sites) is
kept in a ``Hierarchy`` so the writer reproduces the skeleton.  The frame rate is
``1 / Frame Time``, snapped to a whole number when within 0.05% of one (CMU's BVH files say
``0.0083333``, i.e. 120 Hz); the exact frame time is kept in ``meta["frame_time"]``.  CMU's
BVH frame 0 is a T-pose: here it is just a frame.

References
----------
Meredith & Maddock, "Motion capture file formats explained", University of Sheffield (2001).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

from lacuna.errors import ParseError
from mocap.atomic import atomic_write_text
from mocap.motion import Motion

BVH_CHANNELS = {
    "Xposition": "tx", "Yposition": "ty", "Zposition": "tz",
    "Xrotation": "rx", "Yrotation": "ry", "Zrotation": "rz",
}
_DOF_TO_BVH = {v: k for k, v in BVH_CHANNELS.items()}
# Relative distance from a whole number within which 1/frame_time is taken as that number.
FPS_SNAP_REL = 5e-4


@dataclass
class Joint:
    """One node of the hierarchy: a ROOT, a JOINT or an End Site (``channels`` empty).

    ``parent`` is the index of the parent node in ``Hierarchy.joints`` (None for a root).
    ``channels`` are the BVH names (``Zrotation``), in file order.
    """

    name: str
    kind: str  # "ROOT", "JOINT" or "End Site"
    offset: tuple[float, float, float]
    channels: list[str] = field(default_factory=list)
    parent: int | None = None


@dataclass
class Hierarchy:
    """A BVH skeleton: nodes in file order (depth first), as the writer needs them."""

    joints: list[Joint]
    source: str = ""

    @property
    def channels(self) -> list[str]:
        """Motion channel names, ``Joint.rx`` style, in file column order."""
        return [f"{j.name}.{BVH_CHANNELS[c]}" for j in self.joints for c in j.channels]

    def children(self, index: int) -> list[int]:
        return [i for i, j in enumerate(self.joints) if j.parent == index]


class _Tokens:
    """Whitespace tokens of the HIERARCHY part, each with its line number."""

    def __init__(self, lines: list[str], path: str):
        self.path = path
        self.toks: list[tuple[str, int]] = []
        self.end_line = 0  # line index (0-based) of MOTION, or len(lines)
        for i, raw in enumerate(lines):
            if raw.strip().upper() == "MOTION":
                self.end_line = i
                break
            self.toks.extend((t, i + 1) for t in raw.split())
        else:
            self.end_line = len(lines)
        self.pos = 0

    def peek(self) -> str | None:
        return self.toks[self.pos][0] if self.pos < len(self.toks) else None

    def line(self) -> int:
        if self.pos < len(self.toks):
            return self.toks[self.pos][1]
        return self.toks[-1][1] if self.toks else 1

    def next(self, what: str) -> str:
        if self.pos >= len(self.toks):
            raise ParseError(self.path, self.line(), f"hierarchy ends where {what} was expected (truncated?)")
        t = self.toks[self.pos][0]
        self.pos += 1
        return t

    def expect(self, word: str) -> None:
        ln = self.line()
        t = self.next(repr(word))
        if t != word:
            raise ParseError(self.path, ln, f"expected {word!r}, got {t!r}")

    def number(self, what: str) -> float:
        ln = self.line()
        t = self.next(what)
        try:
            v = float(t)
        except ValueError:
            raise ParseError(self.path, ln, f"{what}: not a number: {t!r}") from None
        if not math.isfinite(v):
            raise ParseError(self.path, ln, f"{what}: {t!r} is not finite")
        return v


def _parse_node(tk: _Tokens, kind: str, parent: int | None, joints: list[Joint]) -> None:
    ln = tk.line()
    if kind == "End Site":
        name = (joints[parent].name if parent is not None else "") + "_End"
    else:
        name = tk.next(f"a {kind} name")
        if name == "{":
            raise ParseError(tk.path, ln, f"{kind} without a name")
    tk.expect("{")
    tk.expect("OFFSET")
    off = tuple(tk.number(f"OFFSET of {name}") for _ in range(3))
    node = Joint(name, kind, off, [], parent)  # type: ignore[arg-type]
    joints.append(node)
    me = len(joints) - 1
    if kind != "End Site":
        ln = tk.line()
        tk.expect("CHANNELS")
        ln = tk.line()
        t = tk.next("a channel count")
        try:
            n = int(t)
        except ValueError:
            raise ParseError(tk.path, ln, f"CHANNELS of {name}: count {t!r} is not a whole number") from None
        if not 0 <= n <= 6:
            raise ParseError(tk.path, ln, f"CHANNELS of {name}: count {n} (a joint has 0 to 6)")
        for _ in range(n):
            ln = tk.line()
            c = tk.next(f"a channel of {name}")
            if c not in BVH_CHANNELS:
                raise ParseError(tk.path, ln, f"{name}: unknown channel {c!r} (expected one of {', '.join(BVH_CHANNELS)})")
            if c in node.channels:
                raise ParseError(tk.path, ln, f"{name}: channel {c} listed twice")
            node.channels.append(c)
    while True:
        ln = tk.line()
        t = tk.next(f"'}}' closing {name}")
        if t == "}":
            return
        if kind == "End Site":
            raise ParseError(tk.path, ln, f"End Site of {joints[parent].name if parent is not None else '?'}: expected '}}', got {t!r}")
        if t == "JOINT":
            _parse_node(tk, "JOINT", me, joints)
        elif t == "End":
            ln = tk.line()
            if tk.next("'Site'") != "Site":
                raise ParseError(tk.path, ln, "expected 'End Site'")
            _parse_node(tk, "End Site", me, joints)
        else:
            raise ParseError(tk.path, ln, f"in {name}: expected JOINT, End Site or '}}', got {t!r}")


def parse_bvh(text: str, path: str = "<bvh>") -> Motion:
    """Parse BVH text into a Motion.

    Returns
    -------
    Motion with ``frames`` (n_frames, n_channels), ``skeleton`` a Hierarchy, ``fps``, and
    ``meta["frame_time"]`` (seconds, as written in the file).

    Raises ParseError naming the file and line for a bad header, hierarchy or frame line, a
    missing MOTION section, NaN/inf values, or a ``Frames:`` count that disagrees with the
    frame lines that arrived (trailing blank lines are fine).
    """
    lines = text.splitlines()
    first = next((i for i, ln in enumerate(lines) if ln.strip()), None)
    if first is None:
        raise ParseError(path, None, "empty file (expected a BVH file starting with HIERARCHY)")
    if lines[first].strip() != "HIERARCHY":
        raise ParseError(path, first + 1, f"not a BVH file: expected 'HIERARCHY', got {lines[first].strip()[:40]!r}")
    tk = _Tokens(lines[first + 1 :], path)
    # tokens carry line numbers relative to lines[first+1:]; shift them to file lines.
    tk.toks = [(t, ln + first + 1) for t, ln in tk.toks]
    joints: list[Joint] = []
    while tk.peek() is not None:
        ln = tk.line()
        t = tk.next("ROOT")
        if t != "ROOT":
            raise ParseError(path, ln, f"expected ROOT or MOTION, got {t!r}")
        _parse_node(tk, "ROOT", None, joints)
    if not joints:
        raise ParseError(path, first + 1, "HIERARCHY has no ROOT")
    names = [j.name for j in joints if j.kind != "End Site"]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup:
        raise ParseError(path, None, f"joint name {dup!r} appears twice")
    hier = Hierarchy(joints, path)
    n_ch = len(hier.channels)

    m = first + 1 + tk.end_line  # index of the MOTION line
    if m >= len(lines):
        raise ParseError(path, len(lines), "no MOTION section after the hierarchy (truncated?)")

    def header(idx: int, key: str) -> str:
        if idx >= len(lines):
            raise ParseError(path, len(lines), f"file ends before the '{key}' line (truncated?)")
        ln = lines[idx].strip()
        if not ln.lower().startswith(key.lower()):
            raise ParseError(path, idx + 1, f"expected '{key} ...', got {ln[:40]!r}")
        return ln[len(key) :].strip()

    v = header(m + 1, "Frames:")
    try:
        n_frames = int(v)
    except ValueError:
        raise ParseError(path, m + 2, f"Frames: {v!r} is not a whole number") from None
    if n_frames < 0:
        raise ParseError(path, m + 2, f"Frames: {n_frames} is negative")
    v = header(m + 2, "Frame Time:")
    try:
        frame_time = float(v)
    except ValueError:
        raise ParseError(path, m + 3, f"Frame Time: {v!r} is not a number") from None
    if not (math.isfinite(frame_time) and frame_time > 0):
        raise ParseError(path, m + 3, f"Frame Time: {v} must be a positive number of seconds")

    body = lines[m + 3 :]
    while body and not body[-1].strip():
        body.pop()
    if len(body) != n_frames:
        more = "" if len(body) > n_frames else " (truncated?)"
        raise ParseError(path, m + 2, f"Frames: {n_frames} but {len(body)} frame lines arrived{more}")
    frames = np.empty((n_frames, n_ch))
    for t, ln in enumerate(body):
        lineno = m + 4 + t
        parts = ln.split()
        if len(parts) != n_ch:
            raise ParseError(path, lineno, f"frame {t} has {len(parts)} values, the hierarchy has {n_ch} channels")
        try:
            frames[t] = [float(p) for p in parts]
        except ValueError:
            bad = next(p for p in parts if not _is_float(p))
            raise ParseError(path, lineno, f"frame {t}: not a number: {bad!r}") from None
        if not np.isfinite(frames[t]).all():
            j = int(np.flatnonzero(~np.isfinite(frames[t]))[0])
            raise ParseError(path, lineno, f"frame {t}: channel {hier.channels[j]} is {parts[j]!r} (NaN/inf)")
    return Motion(frames, hier.channels, _fps(frame_time), hier, path, {"frame_time": frame_time})


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _fps(frame_time: float) -> float:
    fps = 1.0 / frame_time
    r = round(fps)
    return float(r) if r > 0 and abs(fps - r) <= FPS_SNAP_REL * r else fps


def read_bvh(path: str | os.PathLike) -> Motion:
    """Read a BVH file (see ``parse_bvh``)."""
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as fh:
            text = fh.read()
    except OSError as e:
        raise ParseError(path, None, f"cannot read ({e.strerror or e})") from None
    return parse_bvh(text, path)


def _num(x: float) -> str:
    # repr is the shortest text that parses back to the same double: exact round trips.
    return repr(float(x)) if x != 0 else "0"


def format_bvh(motion: Motion, hierarchy: Hierarchy | None = None) -> str:
    """BVH text for a motion: the hierarchy's channels, in its column order, full precision.

    The frame time is ``meta["frame_time"]`` when it matches ``motion.fps`` (so a file read and
    written keeps its own ``Frame Time`` text), else ``1 / fps``.
    """
    hier = hierarchy or motion.skeleton
    if not isinstance(hier, Hierarchy):
        raise ValueError(f"writing BVH needs a BVH hierarchy ({motion.source or 'this motion'} has none)")  # noqa: TRY004 (a user-facing error the CLI prints as one line)
    want = hier.channels
    extra = sorted(set(motion.channels) - set(want))
    if extra:
        raise ValueError(f"cannot write BVH: {len(extra)} channels are not in the hierarchy ({', '.join(extra[:4])})")
    frames = motion.frames[:, motion.index(want)]
    bad = np.argwhere(~np.isfinite(frames))
    if len(bad):
        t, j = bad[0]
        raise ValueError(f"cannot write BVH: frame {t} channel {want[j]} is {frames[t, j]} (fill gaps first)")
    out = ["HIERARCHY"]

    def node(i: int, depth: int) -> None:
        j = hier.joints[i]
        ind = "\t" * depth
        out.append(f"{ind}{'End Site' if j.kind == 'End Site' else j.kind + ' ' + j.name}")
        out.append(f"{ind}{{")
        out.append(f"{ind}\tOFFSET {' '.join(_num(v) for v in j.offset)}")
        if j.kind != "End Site":
            out.append(f"{ind}\tCHANNELS {len(j.channels)}" + "".join(" " + c for c in j.channels))
        for k in hier.children(i):
            node(k, depth + 1)
        out.append(f"{ind}}}")

    for i, j in enumerate(hier.joints):
        if j.parent is None:
            node(i, 0)
    ft = motion.meta.get("frame_time")
    if not (isinstance(ft, float) and ft > 0 and _fps(ft) == motion.fps):
        ft = 1.0 / motion.fps
    out += ["MOTION", f"Frames: {frames.shape[0]}", f"Frame Time: {_num(ft)}"]
    out += [" ".join(_num(v) for v in row) for row in frames]
    return "\n".join(out) + "\n"


def write_bvh(path: str | os.PathLike, motion: Motion, hierarchy: Hierarchy | None = None) -> None:
    """Write a BVH file atomically (see ``format_bvh``)."""
    atomic_write_text(path, format_bvh(motion, hierarchy))
