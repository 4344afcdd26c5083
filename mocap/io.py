"""Read and write motion files by extension: ``.amc`` (with its ASF), ``.bvh``, ``.csv``.

    m = read_motion("07_01.amc")                    # ASF found beside it (CMU layout)
    m = read_motion("take.amc", asf="actor.asf")
    m = read_motion("fill.csv", asf="07.asf")       # attach a skeleton so it can become AMC
    write_motion("out.csv", m); write_motion("out.amc", m)
"""
from __future__ import annotations

import os

from lacuna.errors import ParseError
from mocap.asf import Skeleton, read_amc, read_asf, write_amc
from mocap.bvh import Hierarchy, read_bvh, write_bvh
from mocap.csvio import read_csv, write_csv
from mocap.motion import Motion

FORMATS = (".amc", ".bvh", ".csv")


def _ext(path: str) -> str:
    ext = os.path.splitext(path)[1].lower()
    if ext not in FORMATS:
        raise ValueError(f"{path}: unknown motion format {ext or '(no extension)'!r} (expected {', '.join(FORMATS)})")
    return ext


def _skeleton(asf: str | os.PathLike | Skeleton) -> Skeleton:
    return asf if isinstance(asf, Skeleton) else read_asf(asf)


def read_motion(path: str | os.PathLike, asf: str | os.PathLike | Skeleton | None = None, fps: float | None = None) -> Motion:
    """Read a motion file, dispatching on its extension.

    Parameters
    ----------
    asf : for ``.amc``, the skeleton (else found beside the file); for ``.csv``, a skeleton to
        attach (its channels must be exactly the CSV's) so the motion can be written as AMC.
    fps : for ``.amc`` the frame rate (AMC files do not say; CMU's are 120 Hz); for ``.csv``
        the rate when the file gives none.

    Returns
    -------
    Motion, ``frames`` of shape (n_frames, n_channels).
    """
    path = os.fspath(path)
    ext = _ext(path)
    if ext == ".amc":
        return read_amc(path, asf, fps) if fps else read_amc(path, asf)
    if ext == ".bvh":
        if asf is not None:
            raise ValueError(f"{path}: --asf applies to .amc and .csv files, not BVH (a BVH file carries its skeleton)")
        return read_bvh(path)
    m = read_csv(path, fps=fps)
    if asf is not None:
        skel = _skeleton(asf)
        want, have = set(skel.channels), set(m.channels)
        if want != have:
            missing = [c for c in skel.channels if c not in have]
            extra = [c for c in m.channels if c not in want]
            raise ParseError(
                path, None,
                f"channels do not match skeleton {skel.source or skel.name}: "
                f"missing {len(missing)} ({', '.join(missing[:4])}{' ...' if len(missing) > 4 else ''}), "
                f"extra {len(extra)} ({', '.join(extra[:4])}{' ...' if len(extra) > 4 else ''})",
            )
        m.skeleton = skel
    return m


def write_motion(path: str | os.PathLike, motion: Motion, asf: str | os.PathLike | Skeleton | None = None) -> None:
    """Write a motion file atomically, format by extension.

    ``.amc`` needs an ASF skeleton (the motion's, or ``asf``); ``.bvh`` needs the motion's BVH
    hierarchy; ``.csv`` takes any motion.  Writing never drops a channel: a motion whose
    channels differ from the skeleton's is refused with a message saying which.
    """
    path = os.fspath(path)
    ext = _ext(path)
    if ext == ".amc":
        skel = _skeleton(asf) if asf is not None else motion.skeleton
        if not isinstance(skel, Skeleton):
            raise ValueError(f"{path}: writing AMC needs an ASF skeleton ({motion.source or 'this motion'} has none; pass --asf)")
        write_amc(path, motion, skel)
    elif ext == ".bvh":
        if not isinstance(motion.skeleton, Hierarchy):
            raise ValueError(f"{path}: writing BVH needs a BVH hierarchy; {motion.source or 'this motion'} was not read from BVH")
        write_bvh(path, motion)
    else:
        write_csv(path, motion)
