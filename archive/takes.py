"""Which takes a batch fills, where each output goes, and how a take's real gaps are read.

Arguments are files, directories (searched recursively for takes) and globs (``'takes/*.bvh'``,
``'archive/**/*.amc'``).  A take found under a directory argument keeps its path below that
directory in the output (``--out`` mirrors the tree, so an AMC take's ASF can sit beside it as
in CMU's layout); a file or glob argument lands directly in ``--out``.

Real gaps, per format: a CSV take's empty or ``nan`` cells; a ``.lrec`` recording's own mask;
for AMC, BVH (and CSV) a mask sidecar ``TAKE.EXT.mask.json`` beside the take
(``archive.formats``).  A NaN value read from any file is missing too.
"""
from __future__ import annotations

import glob
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from archive.formats import MASK_SUFFIX, read_mask
from lacuna.errors import LacunaError
from mocap.motion import Motion

TAKE_SUFFIXES = (".amc", ".bvh", ".csv", ".lrec")


@dataclass(frozen=True)
class TakeJob:
    """One take of a batch: ``source`` its file, ``output`` the filled take's path (same format)."""

    index: int
    source: str
    output: str


def _is_take(p: str) -> bool:
    return p.lower().endswith(TAKE_SUFFIXES) and not os.path.basename(p).startswith(".")


def discover(args: list[str], out_dir: str) -> list[TakeJob]:
    """The batch's takes in argument order (a directory's sorted), each once.

    Raises LacunaError for an argument that names nothing, and for two takes that would be
    written to one output path.
    """
    out_dir = os.path.abspath(out_dir)
    pairs: list[tuple[str, str]] = []          # (source, path below out_dir)
    for a in args:
        if os.path.isdir(a):
            found = sorted(str(p) for p in Path(a).rglob("*") if p.is_file() and _is_take(str(p)))
            found = [f for f in found if not os.path.abspath(f).startswith(out_dir + os.sep)]
            if not found:
                raise LacunaError(f"{a}: no takes ({', '.join(TAKE_SUFFIXES)}) in this directory")
            pairs += [(f, os.path.relpath(f, a)) for f in found]
        elif os.path.exists(a):
            if not _is_take(a):
                raise LacunaError(f"{a}: not a take (expected {', '.join(TAKE_SUFFIXES)})")
            pairs.append((a, os.path.basename(a)))
        else:
            found = sorted(f for f in glob.glob(a, recursive=True) if os.path.isfile(f) and _is_take(f))
            if not found:
                raise LacunaError(f"{a}: no such file, and no take matches it as a pattern")
            pairs += [(f, os.path.basename(f)) for f in found]
    seen: dict[str, str] = {}
    jobs: list[TakeJob] = []
    for src, rel in pairs:
        s = os.path.abspath(src)
        if s in seen.values():
            continue
        out = os.path.join(out_dir, rel)
        if out in seen:
            raise LacunaError(f"{src} and {seen[out]} would both be written to {out}; pass their directory instead")
        seen[out] = s
        jobs.append(TakeJob(len(jobs), s, out))
    return jobs


def read_with_gaps(path: str) -> tuple[Motion, np.ndarray]:
    """(motion, known) with ``known`` (T, C) bool False where the take has a real gap.

    Missing values in ``motion.frames`` are NaN.
    """
    from clients import recording

    ext = Path(path).suffix.lower()
    if not os.path.exists(path):
        raise LacunaError(f"{path}: no such file")
    if ext == recording.SUFFIX:
        rec = recording.read_recording(path)
        if not rec.has_raw:
            raise LacunaError(f"{path}: the recording holds no raw frames (recorded with --what filled); nothing to fill")
        m = Motion(rec.raw.copy(), list(rec.channels), rec.fps or recording._estimate_fps(rec.t), None, path,
                   {"lrec_seq": rec.seq, "lrec_t": rec.t, "lrec_stream": rec.stream})
        known = rec.observed & np.isfinite(m.frames)
    elif ext == ".csv":
        from mocap.csvio import read_csv

        m = read_csv(path, allow_missing=True)
        known = np.isfinite(m.frames)
    else:
        from mocap.io import read_motion

        m = read_motion(path)
        known = np.isfinite(m.frames)
    side = path + MASK_SUFFIX
    if os.path.exists(side):
        known &= ~read_mask(side, m.channels, m.n_frames)
    m.frames = np.where(known, m.frames, np.nan)
    return m, known


def readable(path: str) -> None:
    """Give a file written through a temporary name (mode 0600) the process umask's mode."""
    os.chmod(path, 0o666 & ~_umask())


def _umask() -> int:
    try:  # without changing it: os.umask() sets as it reads, a race with other threads
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    return 0o022


def write_filled(path: str, motion: Motion, known: np.ndarray, filled_std: np.ndarray) -> None:
    """Write the filled take atomically in the format its extension names.

    A recording keeps its raw frames and mask and gains a fill record per frame (values,
    filled flags, std), as the daemon's would; other formats get the completed frames.
    """
    ext = Path(path).suffix.lower()
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    if ext == ".lrec":
        _write_recording(path, motion, known, filled_std)
        return
    from mocap.io import write_motion

    write_motion(path, motion)
    readable(path)
    skel = motion.skeleton
    if ext == ".amc" and getattr(skel, "source", None):
        from mocap.asf import write_asf

        # the take's own ASF beside the output under the first name mocap.asf.find_asf looks for,
        # so the output reads by itself with its own skeleton: CMU's <subject>.asf where the take
        # came with it, else <take>.asf (an output folder holds several skeletons: find_asf's
        # "the one ASF in the folder" would give a take another's)
        stem = os.path.basename(path).split(".")[0]
        subj = stem.split("_")[0]
        src = os.path.basename(skel.source)
        asf = os.path.join(os.path.dirname(path), src if src == f"{subj}.asf" else f"{stem}.asf")
        if not os.path.exists(asf):
            write_asf(asf, skel)
            readable(asf)


def _write_recording(path: str, motion: Motion, known: np.ndarray, std: np.ndarray) -> None:
    import tempfile

    from clients.recording import RecordingWriter
    from daemon import wire

    seqs = motion.meta.get("lrec_seq")
    stream = str(motion.meta.get("lrec_stream", "")) or "fill"
    ts = motion.meta.get("lrec_t")
    d = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=".part", dir=d)
    os.close(fd)
    try:
        with RecordingWriter(tmp, motion.channels, motion.fps, stream=stream,
                             source=motion.source) as w:
            for k in range(motion.n_frames):
                seq = int(seqs[k]) if seqs is not None else k
                t = float(ts[k]) if ts is not None else k / motion.fps
                fill = wire.FillMsg(stream, seq, t, motion.frames[k].astype(np.float32), ~known[k],
                                    std[k].astype(np.float32), "ok", "lacuna-fill", 0)
                raw = np.where(known[k], motion.frames[k], np.nan)
                w.write(seq, t, raw, known[k], fill)
            w._fh.flush()
            os.fsync(w._fh.fileno())
        readable(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
