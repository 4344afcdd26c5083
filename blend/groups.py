"""Joint groups of ``default``: which row of the stacking weights each channel uses.

The rows are body parts (``mocap.skelmap.PARTS``: root, torso, head-neck, the four limbs), then
``other`` (a bone no map places) and ``root-pos`` (the root's translation: it weighs apart from
the root's rotations, in length units, and takes no regression).  A channel's part comes from
the skeleton map of its take (mocap/skeletons/*.toml, recognised from the bone names or chosen
with ``--skeleton NAME|FILE``), so the weights fitted on CMU ASF validation takes (per part and
time since the gap began) apply to a BVH take's ``LeftForeArm`` as to an ASF ``lradius``.

A model file records the skeleton map's name and every channel's row (``group`` array); a file
written before that had no record and is read with ``legacy_groups``, the table it was fitted
with (CMU ASF bone names; every other bone ``other``), so it fills as it did.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from mocap import skelmap
from mocap.representation import is_angle

_CMU = skelmap.load("cmu-asf")
# part -> CMU ASF bones (the table `default` had before skeleton maps; kept for legacy_groups)
GROUPS = {p: tuple(b for b, i in _CMU.bones.items() if i.part == p) for p in skelmap.PARTS}
GROUP_NAMES = list(GROUPS) + ["other", "root-pos"]  # root rotations and root translation weigh apart
OTHER = len(GROUPS)
ROOT_POS = len(GROUP_NAMES) - 1
NO_REGRESSION = (0, ROOT_POS)


def _row(part: str, channel: str) -> int:
    if part == "root":
        return 0 if is_angle(channel) else ROOT_POS
    return GROUP_NAMES.index(part) if part in GROUPS else OTHER


def group_of(channel: str) -> int:
    """The row of one channel by the legacy table (CMU ASF names; ``root``/``hips`` the root)."""
    bone = channel.split(".", 1)[0]
    for i, bones in enumerate(GROUPS.values()):
        if bone in bones or (i == 0 and bone.lower() in ("root", "hips")):
            return ROOT_POS if i == 0 and not is_angle(channel) else i
    return OTHER


def legacy_groups(channels: Sequence[str]) -> np.ndarray:
    return np.array([group_of(c) for c in channels], np.int64)


def groups_of(channels: Sequence[str], skeleton: str | skelmap.SkeletonMap | None = None,
              source: str = "") -> tuple[np.ndarray, str]:
    """(C,) rows through the skeleton map (``skeleton`` given, else recognised) and the map's name.

    SkeletonError when ``skeleton`` names no map, or when none is given and no map knows these
    bones; ``groups_or_legacy`` is the lenient form."""
    b = skelmap.Binding.of(channels, skeleton, source)
    return np.array([_row(p, c) for p, c in zip(b.parts, b.channels)], np.int64), b.map.name


def groups_or_legacy(channels: Sequence[str], skeleton: str | skelmap.SkeletonMap | None = None,
                     source: str = "") -> tuple[np.ndarray, str]:
    """``groups_of``; where no skeleton was asked for and none is recognised, the legacy table
    (``""`` for the map: every channel ``other`` but a ``root``/``hips`` bone)."""
    if skeleton is not None:
        return groups_of(channels, skeleton, source)
    try:
        return groups_of(channels, None, source)
    except skelmap.SkeletonError:
        return legacy_groups(channels), ""


def check_groups(group: Any, n_channels: int, where: str) -> np.ndarray:
    """A model file's ``group`` array: (C,) integers naming rows of GROUP_NAMES."""
    from lacuna.modelfile import ModelFileError

    g = np.asarray(group)
    if g.shape != (n_channels,) or g.dtype.kind not in "iu" or (g.size and (g.min() < 0 or g.max() >= len(GROUP_NAMES))):
        raise ModelFileError(f"{where}: 'group' must be {n_channels} integers in 0..{len(GROUP_NAMES) - 1} "
                             f"({', '.join(GROUP_NAMES)})")
    return g.astype(np.int64)


def model_groups(channels: Sequence[str], recorded: Any = None, where: str = "") -> np.ndarray:
    """A DefaultModel's rows: ``recorded`` (a model file's ``group`` array, checked), or
    ``"legacy"`` (a file from before skeleton maps: the table it was fitted with), or None
    (a new model: through the skeleton map recognised from the channels' bones)."""
    if recorded is None:
        return groups_or_legacy(channels)[0]
    if isinstance(recorded, str) and recorded == "legacy":
        return legacy_groups(channels)
    return check_groups(recorded, len(channels), where or "model file")


def limb_channels(group: np.ndarray) -> int:
    """How many channels fall in a body part other than the root (0: the fill only holds)."""
    g = np.asarray(group)
    return int(((g > 0) & (g < OTHER)).sum())
