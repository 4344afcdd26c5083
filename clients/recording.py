"""Recording files (``.lrec``): a live stream saved by ``lacuna record``, read by ``lacuna replay``.

A recording is a sequence of msgpack maps, the wire schema's own encoding, appended one per
frame so a crash loses at most the frame being written:

* header ``{"format": "lacuna-recording", "version": 1, "stream", "channels": [...], "fps",
  "source", "started": ISO time}``
* one map per frame ``{"seq", "t", "angles": float32 LE bytes (raw, NaN where missing),
  "observed": uint8 bytes}`` plus, when the filled frame was recorded, ``"fill": {"angles",
  "filled", "std", "status", "model", "proc_us"}``.

Raw frames are what the capture system sent; filled frames what the daemon answered.  Either
may be absent (``--raw`` / ``--filled`` of ``lacuna record``).
"""
from __future__ import annotations

import datetime as _dt
import os
from dataclasses import dataclass, field
from typing import Any, BinaryIO

import msgpack
import numpy as np

from lacuna.errors import ParseError
from mocap.motion import Motion

FORMAT = "lacuna-recording"
VERSION = 1
SUFFIX = ".lrec"
F32 = np.dtype("<f4")


class RecordingWriter:
    """Append frames to a recording file; flushes after every frame."""

    def __init__(self, path: str | os.PathLike[str], channels: list[str], fps: float | None = None, stream: str = "",
                 source: str = ""):
        self.path = os.fspath(path)
        self.channels = list(channels)
        self._fh: BinaryIO = open(self.path, "wb")
        self._packer = msgpack.Packer(use_bin_type=True)
        self.n_frames = 0
        self._write({"format": FORMAT, "version": VERSION, "stream": stream, "channels": self.channels,
                     "fps": fps, "source": source,
                     "started": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")})

    def _write(self, m: dict[str, Any]) -> None:
        self._fh.write(self._packer.pack(m))
        self._fh.flush()

    def write(self, seq: int, t: float, angles: np.ndarray | None = None, observed: np.ndarray | None = None,
              fill: Any = None) -> None:
        """One frame: raw ``angles`` (C,) with ``observed`` (C,) bool, and/or ``fill`` (a wire.FillMsg)."""
        C = len(self.channels)
        rec: dict[str, Any] = {"seq": int(seq), "t": float(t)}
        if angles is not None:
            a = np.asarray(angles, dtype=np.float64)
            if a.shape != (C,):
                raise ValueError(f"{self.path}: frame has {a.shape} values, the recording has {C} channels")
            obs = np.isfinite(a) if observed is None else np.asarray(observed, bool)
            rec["angles"] = np.where(obs, a, np.nan).astype(F32).tobytes()
            rec["observed"] = obs.astype(np.uint8).tobytes()
        if fill is not None:
            if len(fill.angles) != C:
                raise ValueError(f"{self.path}: filled frame has {len(fill.angles)} values, the recording has {C}")
            rec["fill"] = {"angles": np.asarray(fill.angles, F32).tobytes(),
                           "filled": np.asarray(fill.filled, bool).astype(np.uint8).tobytes(),
                           "std": np.asarray(fill.std, F32).tobytes(), "status": fill.status,
                           "model": fill.model, "proc_us": int(fill.proc_us)}
        self._write(rec)
        self.n_frames += 1

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


@dataclass
class Recording:
    """A recording in arrays.

    seq, t : (T,);  raw : (T, C) float64 NaN where not observed (or all NaN when raw was not
    recorded);  observed : (T, C) bool;  filled_angles, std : (T, C) or None;  filled : (T, C)
    bool or None;  status : list of T strings (empty when no fill was recorded).
    """

    channels: list[str]
    fps: float | None
    stream: str
    source: str
    seq: np.ndarray
    t: np.ndarray
    raw: np.ndarray
    observed: np.ndarray
    filled_angles: np.ndarray | None = None
    filled: np.ndarray | None = None
    std: np.ndarray | None = None
    status: list[str] = field(default_factory=list)

    @property
    def has_raw(self) -> bool:
        return bool(self.observed.any())

    def to_motion(self, path: str = "") -> Motion:
        """The take as a Motion: raw values where observed, else the daemon's fill, else NaN."""
        frames = self.raw.copy()
        if self.filled_angles is not None:
            frames = np.where(self.observed, frames, self.filled_angles)
        fps = self.fps or _estimate_fps(self.t)
        return Motion(frames, list(self.channels), fps, None, path or self.source,
                      {"recording_observed": self.observed.copy()})


def _estimate_fps(t: np.ndarray) -> float:
    if t.size < 2:
        return 120.0
    d = np.diff(t)
    d = d[d > 0]
    return float(1.0 / np.median(d)) if d.size else 120.0


def read_recording(path: str | os.PathLike[str]) -> Recording:
    """Read a ``.lrec`` file; ParseError naming the file and the record for anything malformed.

    A truncated last record (the recorder was killed mid-write) is ignored.
    """
    path = os.fspath(path)
    with open(path, "rb") as fh:
        unpacker = msgpack.Unpacker(fh, raw=False, strict_map_key=False, max_buffer_size=1 << 26)
        try:
            head = next(unpacker)
        except StopIteration:
            raise ParseError(path, None, "empty file, not a lacuna recording") from None
        except (ValueError, msgpack.UnpackException) as e:
            raise ParseError(path, None, f"not a lacuna recording ({e})") from None
        if not isinstance(head, dict) or head.get("format") != FORMAT:
            raise ParseError(path, None, f"not a lacuna recording (header {str(head)[:60]})")
        if head.get("version") != VERSION:
            raise ParseError(path, None, f"recording version {head.get('version')!r} is not supported (reads {VERSION})")
        channels = head.get("channels")
        if not isinstance(channels, list) or not channels or not all(isinstance(c, str) for c in channels):
            raise ParseError(path, None, "header 'channels' must be a list of channel names")
        C = len(channels)
        seq, ts, raw, obs, fa, ff, fs, st = [], [], [], [], [], [], [], []
        any_fill = False
        n = 0
        while True:
            try:
                rec = next(unpacker)
            except StopIteration:
                break
            except (ValueError, msgpack.UnpackException):
                break  # truncated tail
            n += 1
            try:
                seq.append(int(rec["seq"]))
                ts.append(float(rec["t"]))
                if "angles" in rec:
                    raw.append(_arr(rec["angles"], F32, C))
                    obs.append(_arr(rec["observed"], np.uint8, C).astype(bool))
                else:
                    raw.append(np.full(C, np.nan))
                    obs.append(np.zeros(C, bool))
                f = rec.get("fill")
                if f is not None:
                    any_fill = True
                    fa.append(_arr(f["angles"], F32, C))
                    ff.append(_arr(f["filled"], np.uint8, C).astype(bool))
                    fs.append(_arr(f["std"], F32, C))
                    st.append(str(f.get("status", "")))
                else:
                    fa.append(np.full(C, np.nan))
                    ff.append(np.zeros(C, bool))
                    fs.append(np.zeros(C))
                    st.append("")
            except (KeyError, TypeError, ValueError) as e:
                raise ParseError(path, None, f"frame record {n} is malformed ({type(e).__name__}: {e})") from None
    if not seq:
        raise ParseError(path, None, "the recording holds no frames")
    R = Recording(channels, head.get("fps"), str(head.get("stream", "")), str(head.get("source", "")),
                  np.array(seq), np.array(ts), np.vstack(raw).astype(np.float64), np.vstack(obs))
    if any_fill:
        R.filled_angles, R.filled, R.std, R.status = np.vstack(fa).astype(np.float64), np.vstack(ff), np.vstack(fs), st
    return R


def _arr(b: Any, dtype: Any, n: int) -> np.ndarray:
    if not isinstance(b, bytes) or len(b) != np.dtype(dtype).itemsize * n:
        got = len(b) if isinstance(b, bytes) else type(b).__name__
        raise ValueError(f"expected {np.dtype(dtype).itemsize * n} bytes for {n} channels (got {got})")
    return np.frombuffer(b, dtype=dtype).astype(np.float64 if dtype is F32 else dtype)


def write_motion_recording(path: str | os.PathLike[str], motion: Motion, observed: np.ndarray | None = None,
                           fills: list[Any] | None = None) -> None:
    """Write a whole take as a recording (replay's output for a recording input)."""
    with RecordingWriter(path, motion.channels, motion.fps, source=motion.source) as w:
        for k in range(motion.n_frames):
            w.write(k, k / motion.fps, motion.frames[k], None if observed is None else observed[k],
                    None if fills is None else fills[k])
