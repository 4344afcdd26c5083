"""The two JSON files of a batch fill: the mask sidecar a take may bring, and the fill sidecar
written beside every filled take (docs/ARCHIVE.md has both with examples).

Masks are run-length encoded per channel: ``{"lhumerus.rx": [[120, 240], [900, 960]]}`` lists
the half-open frame ranges [start, stop) of one channel, in order; a channel absent from the map
has no run.  A mask of 2,000 frames with a 200-frame arm dropout is a few dozen numbers, not
124,000 booleans.

* mask sidecar ``TAKE.EXT.mask.json`` (input, for AMC/BVH/CSV takes whose file format cannot
  say what was lost): ``{"format": "lacuna-mask", "version": 1, "frames": T, "missing": RUNS}``;
  optional ``"channels"`` (checked against the take's when present).
* fill sidecar ``OUT.EXT.fill.json`` (output): which values were filled (``"filled": RUNS``),
  their standard deviations (``"std"``: per channel, one number per filled frame in the order
  of its runs), the method, the model file and its sha256, the input and its sha256, and the
  take's counts.  Written last, atomically: an output without its sidecar is not complete.
"""
from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from lacuna.errors import LacunaError
from mocap.atomic import atomic_write_text

MASK_FORMAT = "lacuna-mask"
FILL_FORMAT = "lacuna-fill"
VERSION = 1
MASK_SUFFIX = ".mask.json"
FILL_SUFFIX = ".fill.json"
STD_DIGITS = 4          # significant digits kept of each filled value's std
HASH_CHUNK_BYTES = 1 << 20


def runs_encode(mask: np.ndarray, channels: Sequence[str]) -> dict[str, list[list[int]]]:
    """(T, C) bool -> {channel: [[start, stop], ...]} for the True runs of each channel."""
    mask = np.asarray(mask, bool)
    out: dict[str, list[list[int]]] = {}
    for j in np.flatnonzero(mask.any(0)):
        edges = np.flatnonzero(np.diff(np.r_[0, mask[:, j].astype(np.int8), 0]))
        out[channels[j]] = [[int(a), int(b)] for a, b in zip(edges[::2], edges[1::2])]
    return out


def runs_decode(runs: dict[str, Any], channels: Sequence[str], n_frames: int, what: str = "mask") -> np.ndarray:
    """{channel: [[start, stop], ...]} -> (T, C) bool; LacunaError naming what is wrong."""
    if not isinstance(runs, dict):
        raise LacunaError(f"{what}: runs must be a map of channel -> [[start, stop], ...] (got {type(runs).__name__})")
    pos = {c: i for i, c in enumerate(channels)}
    mask = np.zeros((n_frames, len(channels)), bool)
    for ch, rr in runs.items():
        if ch not in pos:
            raise LacunaError(f"{what}: channel {ch!r} is not in the take")
        if not isinstance(rr, list):
            raise LacunaError(f"{what}: runs of {ch} must be a list of [start, stop] pairs")
        for r in rr:
            if (not isinstance(r, list) or len(r) != 2 or not all(isinstance(v, int) and not isinstance(v, bool) for v in r)
                    or not 0 <= r[0] < r[1] <= n_frames):
                raise LacunaError(f"{what}: run {r!r} of {ch} is not [start, stop] with 0 <= start < stop <= {n_frames}")
            mask[r[0]:r[1], pos[ch]] = True
    return mask


def std_encode(std: np.ndarray, filled: np.ndarray, channels: Sequence[str]) -> dict[str, list[float]]:
    """Per channel, the std of each filled value in frame order (the order of its runs)."""
    out = {}
    for j in np.flatnonzero(filled.any(0)):
        out[channels[j]] = [float(f"{v:.{STD_DIGITS}g}") for v in std[filled[:, j], j]]
    return out


def std_decode(side: dict[str, Any], channels: Sequence[str]) -> np.ndarray:
    """The (T, C) std array of a fill sidecar (0 where not filled)."""
    T = int(side["frames"])
    filled = runs_decode(side["filled"], channels, T, "fill sidecar")
    std = np.zeros((T, len(channels)))
    pos = {c: i for i, c in enumerate(channels)}
    for ch, vals in side["std"].items():
        j = pos[ch]
        std[filled[:, j], j] = vals
    return std


def read_mask(path: str, channels: Sequence[str], n_frames: int) -> np.ndarray:
    """The missing mask (T, C) of a mask sidecar; LacunaError for anything malformed."""
    try:
        with open(path, encoding="utf-8") as fh:
            d = json.load(fh)
    except (OSError, json.JSONDecodeError) as e:
        raise LacunaError(f"{path}: cannot read mask sidecar ({e})") from None
    if not isinstance(d, dict) or d.get("format") != MASK_FORMAT:
        raise LacunaError(f"{path}: not a {MASK_FORMAT} file")
    if d.get("version") != VERSION:
        raise LacunaError(f"{path}: mask version {d.get('version')!r} is not supported (reads {VERSION})")
    if d.get("frames") != n_frames:
        raise LacunaError(f"{path}: mask is for {d.get('frames')} frames, the take has {n_frames}")
    if "channels" in d and list(d["channels"]) != list(channels):
        raise LacunaError(f"{path}: mask channels differ from the take's ({len(d['channels'])} vs {len(channels)})")
    return runs_decode(d.get("missing", {}), channels, n_frames, path)


def write_mask(path: str, missing: np.ndarray, channels: Sequence[str]) -> None:
    """Write a mask sidecar for a take (e.g. to hand an AMC take's known dropouts to ``lacuna fill``)."""
    d = {"format": MASK_FORMAT, "version": VERSION, "frames": int(missing.shape[0]), "channels": list(channels),
         "missing": runs_encode(missing, channels)}
    atomic_write_text(path, json.dumps(d, indent=1) + "\n")


def sha256_file(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(HASH_CHUNK_BYTES):
            h.update(chunk)
    return h.hexdigest()


def fill_sidecar(*, source: str, source_sha256: str, output: str, method: str, causal: bool,
                 model: dict[str, Any] | None, drop: str | None, channels: Sequence[str], fps: float,
                 filled: np.ndarray, std: np.ndarray, held: np.ndarray, extra: dict[str, Any]) -> dict[str, Any]:
    """The fill sidecar's content (see the module docstring); ``held`` (T, C) marks values of
    channels the model lacks, held from their last value instead of filled by it."""
    return {
        "format": FILL_FORMAT, "version": VERSION, "complete": True,
        "source": source, "source_sha256": source_sha256, "output": os.path.basename(output),
        "method": method, "causal": bool(causal), "model": model, "drop": drop,
        "frames": int(filled.shape[0]), "fps": float(fps), "channels": list(channels),
        "values_filled": int(filled.sum()), "filled": runs_encode(filled, channels),
        "std": std_encode(std, filled, channels), "held": runs_encode(held, channels), **extra,
    }


def read_fill_sidecar(path: str) -> dict[str, Any] | None:
    """A fill sidecar's content, or None when it is absent, unreadable or not complete."""
    try:
        with open(path, encoding="utf-8") as fh:
            d = json.load(fh)
    except (OSError, json.JSONDecodeError):
        return None
    if not isinstance(d, dict) or d.get("format") != FILL_FORMAT or d.get("version") != VERSION or not d.get("complete"):
        return None
    return d
