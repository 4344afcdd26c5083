"""Skeletons as data: which bone is which body part, for every naming Lacuna knows.

A skeleton map is a small TOML file (the shipped ones are ``mocap/skeletons/*.toml``)::

    name = "humanik"                 # what --skeleton NAME selects
    description = "..."
    format = "bvh"                   # "asf": a bone's dofs rotate that bone; "bvh": a joint's
                                     # channels rotate the segment to its children
    up = "y"                         # the world's vertical axis
    length_unit = 0.01               # optional: metres per file unit (else the file's or a guess)
    [root]
    bone = "Hips"                    # the root bone; its channels are BONE.tx/.ty/.tz, .rx/.ry/.rz
    translation = ["tx", "ty", "tz"] # the root's translation dofs along x, y, z
    order = "zxy"                    # R = Rz Rx Ry, used when a file does not declare its own
    rest = [90, 0, 0]                # optional: root rotation x, y, z (degrees) standing upright
    [bones]
    LeftArm = { part = "left-arm", side = "left", parent = "LeftShoulder", order = "zxy" }
    [[patterns]]                     # optional: names that follow a rule (full-match regex)
    match = "LeftHand(Thumb|Index|Middle|Ring|Pinky)[0-9]"
    part = "left-arm"
    side = "left"

Parts are ``root`` (never erased by a drop pattern) and the six joint groups of GROUPS.
A file's bone names are matched exactly, then without a ``prefix:`` or ``prefix_`` in front
(``mixamorig:LeftArm``, ``Skeleton_LThigh``), case-insensitively.  ``recognise`` picks the
map that knows the most of a take's bones (then the one most of whose bones the take has) and
raises SkeletonError when none knows most (MIN_KNOWN) of its bones.
"""
from __future__ import annotations

import re
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lacuna.errors import LacunaError

MAP_DIR = Path(__file__).with_name("skeletons")
PARTS = ("root", "torso", "head-neck", "left-arm", "right-arm", "left-leg", "right-leg")
# the joint groups a drop pattern or the gaps protocol erases (CMU ASF order of the old JOINT_GROUPS)
GROUPS = ("left-arm", "right-arm", "left-leg", "right-leg", "head-neck", "torso")
COMPOSITES = {
    "legs": ("left-leg", "right-leg"),
    "arms": ("left-arm", "right-arm"),
    "upper-body": ("torso", "head-neck", "left-arm", "right-arm"),
}
MIN_KNOWN = 0.6  # fraction of a take's bones a map must know to be recognised
_AXES = "xyz"


class SkeletonError(LacunaError):
    """A skeleton map cannot be loaded, or no map fits a take."""


@dataclass(frozen=True)
class BoneInfo:
    part: str
    side: str = "center"
    parent: str = ""
    order: str = ""


@dataclass
class SkeletonMap:
    name: str
    description: str
    format: str
    up: str
    root_bone: str
    translation: tuple[str, str, str]
    root_order: str
    bones: dict[str, BoneInfo]
    root_rest: tuple[float, float, float] | None = None
    patterns: list[tuple[re.Pattern[str], BoneInfo]] = field(default_factory=list)
    length_unit: float | None = None
    source: str = ""

    def __post_init__(self) -> None:
        self._lower = {k.lower(): k for k in self.bones}

    def canonical(self, bone: str) -> str | None:
        """The map's name for a file's bone (``mixamorig:LeftArm`` -> ``LeftArm``), or None."""
        for cand in _candidates(bone):
            k = self._lower.get(cand.lower())
            if k is not None:
                return k
        return None

    def lookup(self, bone: str) -> BoneInfo | None:
        k = self.canonical(bone)
        if k is not None:
            return self.bones[k]
        for cand in _candidates(bone):
            for rx, info in self.patterns:
                if rx.fullmatch(cand):
                    return info
        return None

    def score(self, bones: Sequence[str]) -> tuple[float, float, int]:
        """(fraction of ``bones`` this map knows, fraction of the map's named bones present,
        number of them): the best map knows most of the take, then has least the take lacks,
        then names the most of it (a map that lists Spine3 beats one whose pattern allows it)."""
        bones = list(dict.fromkeys(bones))
        if not bones:
            return 0.0, 0.0, 0
        known = sum(self.lookup(b) is not None for b in bones)
        named = {self.canonical(b) for b in bones} - {None}
        return known / len(bones), len(named) / max(1, len(self.bones)), len(named)


def _candidates(bone: str) -> list[str]:
    out = [bone]
    if ":" in bone:
        out.append(bone.rsplit(":", 1)[1])
    s = out[-1]
    while "_" in s:
        s = s.split("_", 1)[1]
        if s:
            out.append(s)
    return out


def _check_order(order: str, where: str) -> str:
    o = order.lower()
    if o and (set(o) - set(_AXES) or len(set(o)) != len(o)):
        raise SkeletonError(f"{where}: rotation order {order!r} must be axes x, y, z, each at most once")
    return o


def parse_map(text: str, source: str = "<map>") -> SkeletonMap:
    """A SkeletonMap from TOML text; SkeletonError naming the file and the bad entry."""
    try:
        d = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise SkeletonError(f"{source}: not a valid TOML skeleton map ({e})") from None

    def need(key: str, table: dict[str, Any] = d, where: str = "") -> Any:
        if key not in table:
            raise SkeletonError(f"{source}: missing {where}{key!r}")
        return table[key]

    root = need("root")
    bones_t = need("bones")
    if not isinstance(bones_t, dict) or not bones_t:
        raise SkeletonError(f"{source}: [bones] must map bone names to {{part, side, parent, order}}")
    bones: dict[str, BoneInfo] = {}
    for name, b in bones_t.items():
        if not isinstance(b, dict) or "part" not in b:
            raise SkeletonError(f"{source}: bone {name!r} needs a part (one of {', '.join(PARTS)})")
        if b["part"] not in PARTS:
            raise SkeletonError(f"{source}: bone {name!r}: unknown part {b['part']!r} (known: {', '.join(PARTS)})")
        bones[name] = BoneInfo(b["part"], b.get("side", "center"), b.get("parent", ""),
                               _check_order(b.get("order", ""), f"{source}: bone {name!r}"))
    patterns = []
    for p in d.get("patterns", []):
        if "match" not in p or p.get("part") not in PARTS:
            raise SkeletonError(f"{source}: a [[patterns]] entry needs match and a part (one of {', '.join(PARTS)})")
        try:
            rx = re.compile(p["match"], re.IGNORECASE)
        except re.error as e:
            raise SkeletonError(f"{source}: pattern {p['match']!r}: {e}") from None
        patterns.append((rx, BoneInfo(p["part"], p.get("side", "center"))))
    rb = need("bone", root, "[root] ")
    if rb not in bones:
        raise SkeletonError(f"{source}: root bone {rb!r} is not in [bones]")
    tr = tuple(root.get("translation", ("tx", "ty", "tz")))
    if len(tr) != 3:
        raise SkeletonError(f"{source}: [root] translation names three dofs (x, y, z)")
    up = str(d.get("up", "y")).lower()
    if up not in _AXES:
        raise SkeletonError(f"{source}: up must be x, y or z (got {up!r})")
    fmt = d.get("format", "bvh")
    if fmt not in ("asf", "bvh"):
        raise SkeletonError(f"{source}: format must be 'asf' or 'bvh' (got {fmt!r})")
    lu = d.get("length_unit")
    if lu is not None and not (isinstance(lu, (int, float)) and lu > 0):
        raise SkeletonError(f"{source}: length_unit must be a positive number of metres (got {lu!r})")
    rest = root.get("rest")
    if rest is not None and (len(rest) != 3 or not all(isinstance(v, (int, float)) for v in rest)):
        raise SkeletonError(f"{source}: [root] rest is the root's x, y, z rotation (degrees) standing upright")
    return SkeletonMap(str(need("name")), str(d.get("description", "")), fmt, up, rb, tr,  # type: ignore[arg-type]
                       _check_order(root.get("order", "zyx"), f"{source}: [root]"), bones,
                       None if rest is None else tuple(float(v) for v in rest),  # type: ignore[arg-type]
                       patterns, None if lu is None else float(lu), source)


_CACHE: dict[str, SkeletonMap] = {}


def available() -> list[str]:
    """Names of the shipped maps."""
    return sorted(p.stem for p in MAP_DIR.glob("*.toml"))


def load(spec: str) -> SkeletonMap:
    """A shipped map by name (``humanik``) or a map file by path (``studio.toml``)."""
    if spec in _CACHE:
        return _CACHE[spec]
    p = Path(spec)
    if p.suffix.lower() != ".toml" or not p.exists():
        cand = MAP_DIR / f"{spec}.toml"
        if not cand.exists():
            if p.suffix.lower() == ".toml":
                raise SkeletonError(f"--skeleton {spec}: no such file")
            raise SkeletonError(f"--skeleton {spec}: unknown skeleton (known: {', '.join(available())}; "
                                "or give a .toml map file)")
        p = cand
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as e:
        raise SkeletonError(f"{p}: cannot read ({e.strerror or e})") from None
    m = parse_map(text, str(p))
    _CACHE[spec] = m
    return m


def bones_of(channels: Sequence[str]) -> list[str]:
    """Bone names of ``bone.dof`` channels, in first-seen order."""
    return list(dict.fromkeys(c.rsplit(".", 1)[0] for c in channels))


def recognise(bones: Sequence[str], source: str = "") -> SkeletonMap:
    """The shipped map that fits these bone names best; SkeletonError when none does."""
    bones = list(bones)
    best: tuple[tuple[float, float, int], SkeletonMap] | None = None
    for name in available():
        m = load(name)
        s = m.score(bones)
        if s[0] >= MIN_KNOWN and (best is None or s > best[0]):
            best = (s, m)
    if best is None:
        shown = ", ".join(bones[:6]) + (" ..." if len(bones) > 6 else "")
        raise SkeletonError(f"{source or 'this take'}: its bones ({shown}) match no known skeleton "
                            f"({', '.join(available())}); pass --skeleton NAME or a .toml map file")
    return best[1]


def resolve(spec: str | SkeletonMap | None, channels: Sequence[str], source: str = "") -> SkeletonMap:
    """``--skeleton`` given (name, file or map) or recognised from the channel names."""
    if isinstance(spec, SkeletonMap):
        return spec
    if spec:
        return load(spec)
    return recognise(bones_of(channels), source)


# ---- a map applied to one take's channels --------------------------------------------------------
DEFAULT_ROOT = {"rot": ["root.rx", "root.ry", "root.rz"], "order": "zyx",
                "pos": ["root.tx", "root.ty", "root.tz"], "up": "y"}


@dataclass
class Binding:
    """A skeleton map applied to a channel list: each channel's body part, and the root's channels.

    ``parts`` : per channel, its bone's part (``""`` for a bone the map does not know).
    """

    map: SkeletonMap
    channels: list[str]
    parts: list[str]
    root_bone: str
    source: str = ""

    @classmethod
    def of(cls, channels: Sequence[str], spec: str | SkeletonMap | None = None, source: str = "") -> Binding:
        channels = list(channels)
        m = resolve(spec, channels, source)
        parts, root = [], ""
        for c in channels:
            b = c.rsplit(".", 1)[0]
            info = m.lookup(b)
            parts.append(info.part if info else "")
            if not root and m.canonical(b) == m.root_bone:
                root = b
        return cls(m, channels, parts, root, source)

    def expand(self, groups: Sequence[str] | str) -> list[str]:
        """Group names with composites (legs, arms, upper-body) expanded; SkeletonError for unknown ones."""
        gs = [groups] if isinstance(groups, str) else list(groups)
        out: list[str] = []
        for g in gs:
            if g in COMPOSITES:
                out += COMPOSITES[g]
            elif g in PARTS:
                out.append(g)
            else:
                raise SkeletonError(f"unknown joint group {g!r} (known: {', '.join(GROUPS + tuple(COMPOSITES))})")
        return out

    def mask(self, groups: Sequence[str] | str, what: str = "", require: bool = True) -> Any:
        """(C,) bool: the channels of bones in these groups.  With ``require``, SkeletonError when
        there are none (a drop pattern that would erase nothing), naming the skeleton and groups."""
        import numpy as np

        want = set(self.expand(groups))
        m = np.array([p in want for p in self.parts], dtype=bool)
        if require and not m.any():
            looked = sorted(b for b, i in self.map.bones.items() if i.part in want)
            raise SkeletonError(
                f"{what + ': ' if what else ''}{self.source or 'this take'} (skeleton {self.map.name}) has no channels "
                f"in {', '.join(sorted(want))}: looked for bones {', '.join(looked[:8])}"
                f"{' ...' if len(looked) > 8 else ''}; pass --skeleton NAME|FILE if the take is another skeleton")
        return m

    def bones(self, group: str) -> list[str]:
        """The take's bone names in a group, in channel order."""
        want = set(self.expand(group))
        return list(dict.fromkeys(c.rsplit(".", 1)[0] for c, p in zip(self.channels, self.parts) if p in want))

    def root_spec(self, skeleton: Any = None) -> dict[str, Any] | None:
        """The representation's root description ``{"rot": [x, y, z rotation channels], "order":
        composition order ("zyx": R = Rz Ry Rx), "pos": [x, y, z translation channels], "up"}``;
        None when the take lacks a root rotation or translation channel."""
        r = self.root_bone
        if not r:
            return None
        rot = [f"{r}.r{a}" for a in _AXES]
        pos = [f"{r}.{d}" for d in self.map.translation]
        if any(c not in self.channels for c in rot + pos):
            return None
        spec: dict[str, Any] = {"rot": rot, "order": self._root_order(skeleton), "pos": pos, "up": self.map.up}
        if self.map.root_rest and any(self.map.root_rest):
            spec["rest"] = list(self.map.root_rest)
        return spec

    def _root_order(self, skeleton: Any) -> str:
        from mocap.asf import Skeleton
        from mocap.bvh import BVH_CHANNELS, Hierarchy

        if isinstance(skeleton, Hierarchy):
            j = next((j for j in skeleton.joints if j.name == self.root_bone), None)
            if j is not None:
                o = "".join(BVH_CHANNELS[c][1] for c in j.channels if c.endswith("rotation"))
                if len(o) == 3:
                    return o
        if isinstance(skeleton, Skeleton):
            o = "".join(d[1] for d in skeleton.root_order if d.startswith("r"))
            if len(o) == 3:
                return o[::-1]  # Acclaim dofs apply in listed order: R = R_last ... R_first
        seen = "".join(c.rsplit(".", 1)[1][1] for c in self.channels
                       if c.startswith(self.root_bone + ".") and c.rsplit(".", 1)[1].startswith("r"))
        if len(seen) == 3:
            return seen[::-1] if self.map.format == "asf" else seen
        return self.map.root_order


def add_argument(parser: Any) -> None:
    """``--skeleton NAME|FILE`` on a command that reads motion files."""
    parser.add_argument("--skeleton", metavar="NAME|FILE",
                        help="skeleton map of the motion files: a shipped name (" + ", ".join(available()) +
                        ") or a .toml map file (default: recognised from the bone names)")


def mismatch(model_channels: Sequence[str], take_channels: Sequence[str], source: str = "",
             spec: str | SkeletonMap | None = None, model_skeleton: str = "") -> str | None:
    """Why a model cannot fill a take of another skeleton (None when every model channel is in
    the take).  A model's Gaussian, Euler conventions and channel names are its training
    skeleton's: an ASF ``lfemur.rx`` and a BVH ``LeftUpLeg.rx`` rotate the same thigh about other
    axes from another rest pose, so no renaming makes one model fill the other's takes."""
    mc, tc = list(model_channels), set(take_channels)
    if all(c in tc for c in mc):
        return None

    def name(channels: Sequence[str], s: Any = None, given: str = "") -> str:
        if given:
            return given
        try:
            return resolve(s, channels).name
        except SkeletonError:
            return "an unknown skeleton"

    ms, ts = name(mc, given=model_skeleton), name(list(take_channels), spec)
    if ms == ts:
        missing = [c for c in mc if c not in tc]
        return (f"{source or 'the take'} lacks {len(missing)} of the model's {len(mc)} channels "
                f"(e.g. {', '.join(missing[:3])}): train the model on takes with the same channels")
    return (f"the model was trained on skeleton {ms} ({len(mc)} channels: {', '.join(bones_of(mc)[:3])}, ...) and "
            f"{source or 'the take'} is {ts} ({len(tc)} channels): their angles differ by convention (each "
            f"skeleton's own rest pose, joint axes and rotation order), so a model fills takes of its own skeleton "
            f"only; train one on {ts} takes (lacuna train default TAKE ...)")
