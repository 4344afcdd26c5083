"""Takes for replay, bench and demo: read/write any supported file, and erasure patterns.

Formats: ``.lrec`` recordings (clients/recording.py), ``.amc`` (mocap.asf), and ``.bvh`` /
``.csv`` through ``mocap.io`` when that module is present in this build.

Erasure patterns (``--drop``), from ``mocap/protocols.py``, over the take's joint groups as its
skeleton map (``mocap.skelmap``, recognised by bone names or ``--skeleton``) names them:

* ``none``                              nothing erased
* ``gaps``                              the gaps protocol's seeded bursts on the six joint groups
* ``gaps:left-arm,head-neck,root``      the same bursts, on the named groups only
* ``pan2009``                           second half, everything but the legs
* ``taylor2007:right-leg``              from the middle on, the right leg (or ``upper-body``)

A pattern that would erase nothing (a skeleton without the groups it names) is an error naming
the skeleton and the bones it looked for.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from clients import recording
from lacuna.errors import LacunaError
from mocap import skelmap
from mocap.motion import Motion
from mocap.protocols import GAP_GROUPS, Gaps
from mocap.tpose import skip_tpose


def _io() -> Any:
    try:
        from mocap import io as mio
    except ImportError:  # mocap.io (BVH/CSV) is not in this build yet
        return None
    return mio


def read_take(path: str | os.PathLike[str], asf: str | None = None) -> tuple[Motion, np.ndarray | None]:
    """(motion, observed mask or None).  A recording's own mask says which values were captured."""
    p = os.fspath(path)
    ext = Path(p).suffix.lower()
    if not os.path.exists(p):
        raise LacunaError(f"{p}: no such file")
    if ext == recording.SUFFIX:
        rec = recording.read_recording(p)
        if not rec.has_raw and rec.filled_angles is None:
            raise LacunaError(f"{p}: the recording holds neither raw nor filled frames")
        m = rec.to_motion(p)
        obs = rec.observed if rec.has_raw else np.isfinite(m.frames)
        return m, obs
    mio = _io()
    if mio is not None:
        return skip_tpose(mio.read_motion(p, asf=asf)), None
    if ext == ".amc":
        from mocap.asf import read_amc

        return read_amc(p, asf), None
    raise LacunaError(f"{p}: this build reads .amc and {recording.SUFFIX} takes (mocap.io for BVH/CSV is not installed)")


def write_take(path: str | os.PathLike[str], motion: Motion, asf: str | None = None, observed: np.ndarray | None = None,
               fills: list[Any] | None = None) -> None:
    """Write in the format the extension names (the input's format for replay)."""
    p = os.fspath(path)
    ext = Path(p).suffix.lower()
    if ext == recording.SUFFIX:
        recording.write_motion_recording(p, motion, observed, fills)
        return
    mio = _io()
    if mio is not None:
        mio.write_motion(p, motion, asf=asf)
        return
    if ext == ".amc":
        from mocap.asf import read_asf, write_amc

        write_amc(p, motion, motion.skeleton if asf is None else read_asf(asf))
        return
    raise LacunaError(f"{p}: this build writes .amc and {recording.SUFFIX} (mocap.io for BVH/CSV is not installed)")


def check_pattern(pattern: str) -> None:
    """Reject an unknown drop pattern or joint group before any take is read (LacunaError naming
    it); whether the pattern erases anything depends on each take's skeleton (``drop_mask``)."""
    name, _, arg = pattern.partition(":")
    what = f"--drop {pattern}"
    if name == "none":
        return
    if name not in ("gaps", "pan2009", "taylor2007"):
        raise LacunaError(f"--drop {pattern!r}: unknown pattern (none, gaps[:GROUP,...], pan2009, "
                          "taylor2007:right-leg|upper-body)")
    if name == "gaps":
        bad = [g for g in arg.split(",") if g and g not in GAP_GROUPS]
        if bad:
            raise LacunaError(f"{what}: unknown joint group {bad[0]!r} (known: {', '.join(GAP_GROUPS)})")
    if name == "taylor2007" and arg not in ("", "right-leg", "upper-body"):
        raise LacunaError(f"{what}: taylor2007 erases right-leg or upper-body (got {arg!r})")


def drop_mask(pattern: str, motion: Motion, seed: int = 0, skeleton: str | None = None,
              require_erased: bool = True) -> tuple[np.ndarray, list[tuple[str, int, int]]]:
    """The observed mask (T, C) a pattern leaves, and the bursts (group, start, stop) it erased.

    Raises LacunaError naming the pattern when it is unknown or would erase nothing (with
    ``require_erased=False`` a gaps pattern whose random bursts miss a short take erases nothing).
    """
    T, C = motion.frames.shape
    ch = motion.channels
    obs = np.ones((T, C), bool)
    check_pattern(pattern)
    name, _, arg = pattern.partition(":")
    what = f"--drop {pattern}"
    if name == "none":
        return obs, []
    sk = skelmap.Binding.of(ch, skeleton, motion.source)
    if name == "gaps":
        groups = [g for g in arg.split(",") if g] if arg else list(skelmap.GROUPS)
        sk.mask(groups, what)
        gaps = Gaps(seed)
        gaps.skeleton = skeleton
        _, bursts = gaps.occlusion(Path(motion.source).stem or "take", T, ch, motion.fps)
        keep = [b for b in bursts if b[0] in groups]
        for g, a, b in keep:
            obs[a:b, sk.mask(g, require=False)] = False
        if obs.all() and require_erased:
            raise LacunaError(f"{what}: no burst falls in this take's {T} frames ({T / motion.fps:.2f} s); "
                              "try another --seed or a longer take")
        return obs, keep
    if name == "pan2009":
        legs = sk.mask("legs", what)
        sk.mask(["root", "upper-body"], what)
        obs[T // 2:, ~legs] = False
        return obs, [("all-but-legs", T // 2, T)]
    which = arg or "right-leg"
    obs[T // 2:, sk.mask(which, what)] = False
    return obs, [(which, T // 2, T)]
