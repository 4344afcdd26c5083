"""The view's state: the newest fill of every stream, turned into page updates at a fixed rate.

Frames come in at the capture rate (120 Hz a stream, say) from a PUB subscriber or a player
(``view/sources.py``) through :meth:`Feed.on_fill`, which only keeps the frame and its latency
figures: the newest frame wins.  A ticker (:meth:`Feed.tick`, ``rate`` times a second) turns the
streams that changed into one JSON update: joint positions from forward kinematics
(``mocap.fk``, batched over the streams of a tick), each joint's state and the extras.  So the
cost of the view is bounded by the page's rate, not the capture rate.

Joint state, per joint of the skeleton (sent as ``fill``, one number a joint):
``-1`` observed (none of the joint's channels was filled), ``-2`` held (filled without an
estimate: the daemon's std is NaN), else the largest std (degrees) of its filled channels.
A joint's channels are those named ``joint.dof`` (``rhumerus.rx``).

Latency, per stream: ``proc_ms``, the daemon's own time from reading the frame to encoding its
answer (``proc_us`` of the fill), and ``age_ms``, capture to view: the view's wall clock minus
the frame's capture timestamp ``t``, given only when ``t`` is a wall-clock time (within
``AGE_WINDOW_S`` of now; replays stamp ``t`` from 0).  ``age_ms`` covers both legs of the round
trip (capture to daemon, daemon to a subscriber) plus the fill.
"""
from __future__ import annotations

import json
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from daemon import wire
from mocap.motion import Motion
from view import PAGE_FPS, PAGE_MAX_DPR

AGE_WINDOW_S = 5.0  # a capture timestamp this close to the view's clock is taken as wall-clock time
STATS_EVERY_S = 1.0
STATS_WINDOW_S = 10.0  # percentiles over the last this many seconds
FORGET_S = 30.0  # a stream without a frame for this long leaves the page (the daemon ended it, say)
OBSERVED, HELD = -1.0, -2.0
# the page draws y up; a file with another vertical axis is turned (right-handed) before sending
TO_Y_UP = {"y": np.eye(3), "z": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
           "x": np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])}


def bone(channel: str) -> str:
    return channel.rsplit(".", 1)[0]


class Skeleton:
    """A skeleton ready to place any stream's channels on it.

    The stream's values are put into the skeleton's own channel vector by name; channels the
    stream lacks keep ``base`` (a motion file's first frame; zeros without one).
    """

    def __init__(self, kin: Any, base: np.ndarray | None = None, source: str = ""):
        self.kin = kin
        self.channels = list(kin.channels)
        self.joints = list(kin.joints)
        self.parents = [int(p) for p in kin.parents]
        self.base = np.zeros(len(self.channels)) if base is None else np.asarray(base, np.float64).copy()
        self.source = source
        self.turn = TO_Y_UP[getattr(kin, "up_axis", "y")]

    @classmethod
    def from_motion(cls, motion: Motion) -> Skeleton:
        from mocap.fk import Kinematics  # the one FK (issue 20, part 2)

        return cls(Kinematics.from_motion(motion), motion.frames[0] if motion.n_frames else None, motion.source)

    @classmethod
    def from_model(cls, path: str) -> Skeleton | None:
        """The skeleton a model file was trained on (``meta["training"]["skeleton"]``), or None."""
        from lacuna import modelfile
        from mocap.fk import from_record

        meta, _ = modelfile.load_arrays(path)
        rec = (meta.get("training") or {}).get("skeleton")
        return cls(from_record(rec), None, f"{path} (its training skeleton)") if isinstance(rec, dict) else None

    def mapping(self, stream_channels: list[str]) -> ChannelMap:
        return ChannelMap(self, stream_channels)


class ChannelMap:
    """Where a stream's channels go on a skeleton, and which joint each belongs to."""

    def __init__(self, skel: Skeleton, stream_channels: list[str]):
        pos = {c: i for i, c in enumerate(skel.channels)}
        src = [i for i, c in enumerate(stream_channels) if c in pos]
        if not src:
            raise ValueError(f"none of the stream's {len(stream_channels)} channels is on the skeleton of "
                             f"{skel.source or 'the skeleton file'} (e.g. {stream_channels[:3]})")
        self.width = len(stream_channels)
        self.src = np.asarray(src, int)
        self.dst = np.asarray([pos[stream_channels[i]] for i in src], int)
        jpos = {j: k for k, j in enumerate(skel.joints)}
        member = np.zeros((len(skel.joints), len(stream_channels)), bool)  # (J, C)
        for i, c in enumerate(stream_channels):
            k = jpos.get(bone(c))
            if k is not None:
                member[k, i] = True
        self.member = member
        self.has_channels = member.any(axis=1)

    def frame(self, last: np.ndarray, angles: np.ndarray) -> np.ndarray:
        """The skeleton's channel vector for a stream frame; a NaN value keeps ``last``'s."""
        out = last.copy()
        v = angles[self.src].astype(np.float64)
        ok = np.isfinite(v)
        out[self.dst[ok]] = v[ok]
        return out

    def joint_state(self, filled: np.ndarray, std: np.ndarray) -> np.ndarray:
        """(J,) per-joint state: OBSERVED, HELD or the largest std of the joint's filled channels."""
        f = self.member & filled[None, :]  # (J, C): the joint's filled channels
        finite = np.isfinite(std)[None, :]
        top = np.where(f & finite, std[None, :], -np.inf).max(axis=1, initial=-np.inf)
        held = (f & ~finite).any(axis=1)
        return np.where(f.any(axis=1), np.where(held, HELD, top), OBSERVED)


@dataclass
class StreamState:
    id: str
    channels: list[str] | None = None
    model: str = ""
    msg: wire.FillMsg | None = None
    new: bool = False
    last_frame: np.ndarray | None = None  # skeleton channel vector of the last frame drawn
    cmap: ChannelMap | None = None
    problem: str = ""  # why the stream has no skeleton, for the page
    problem_width: int = 0  # the frame width the problem was found for
    frames: int = 0
    last_seen: float = 0.0  # monotonic time of its newest frame
    tick_proc_ms: float | None = None
    tick_age_ms: float | None = None
    recent: deque = field(default_factory=deque)  # (recv monotonic, proc_ms, age_ms or None)


class Feed:
    """Newest frame per stream in, page updates out (see the module docstring).

    Parameters
    ----------
    skeleton : the skeleton every stream is drawn on, or None (no positions).
    channels : channel names for streams whose names the view does not learn from a hello-ack.
    """

    def __init__(self, skeleton: Skeleton | None, channels: list[str] | None = None, *, rate: float = 30.0,
                 std_max: float = 20.0, mode: str = "live", source: str = "", fps: float = PAGE_FPS,
                 max_dpr: float = PAGE_MAX_DPR):
        if rate <= 0:
            raise ValueError(f"--rate must be > 0 (got {rate})")
        if fps <= 0 or max_dpr <= 0:
            raise ValueError(f"--fps and --max-dpr must be > 0 (got {fps:g}, {max_dpr:g})")
        self.fps, self.max_dpr = fps, max_dpr
        self.skeleton = skeleton
        self.default_channels = list(channels) if channels else None
        self.rate = rate
        self.std_max = std_max
        self.mode = mode
        self.source = source
        self.streams: dict[str, StreamState] = {}
        self.lock = threading.Lock()
        self.meta_version = 0
        self.received = 0
        self.error = ""
        self._next_stats = 0.0

    # ---- in (any thread) ------------------------------------------------------------------------
    def on_ack(self, ack: wire.HelloAck) -> None:
        with self.lock:
            st = self._stream(ack.stream)
            st.channels, st.model = list(ack.channels), ack.model
            st.cmap, st.last_frame, st.problem = None, None, ""
            self.meta_version += 1

    def fail(self, why: str) -> None:
        """A source died: the page says so."""
        with self.lock:
            self.error = why
            self.meta_version += 1

    def on_fill(self, msg: wire.FillMsg, wall: float | None = None, latency: bool = True) -> None:
        """Keep ``msg`` as its stream's newest frame.  ``latency=False``: a played file, whose
        ``proc_us`` and timestamps say nothing about now."""
        now = time.monotonic()
        wall = time.time() if wall is None else wall
        age = (wall - msg.t) * 1000.0 if latency and abs(wall - msg.t) < AGE_WINDOW_S else None
        proc = msg.proc_us / 1000.0 if latency else None
        with self.lock:
            self.received += 1
            st = self._stream(msg.stream)
            if st.model != msg.model:
                st.model = msg.model
                self.meta_version += 1
            st.msg, st.new, st.last_seen = msg, True, now
            st.frames += 1
            if proc is not None:
                st.tick_proc_ms = proc if st.tick_proc_ms is None else max(st.tick_proc_ms, proc)
                st.recent.append((now, proc, age))
            if age is not None:
                st.tick_age_ms = age if st.tick_age_ms is None else max(st.tick_age_ms, age)

    def _stream(self, sid: str) -> StreamState:
        st = self.streams.get(sid)
        if st is None:
            st = self.streams[sid] = StreamState(sid)
            self.meta_version += 1
        return st

    # ---- out (the ticker) -----------------------------------------------------------------------
    def _resolve(self, st: StreamState, width: int) -> None:
        """Find the stream's channel names and its map onto the skeleton (once, or after a hello)."""
        if st.cmap is not None or st.problem:
            return
        st.problem_width = width
        names = st.channels
        if names is not None and len(names) != width:
            names = None  # (the hello-ack was for another channel list)
        if names is None and self.default_channels and len(self.default_channels) == width:
            names = self.default_channels
        if names is None and self.skeleton is not None and len(self.skeleton.channels) == width:
            names = self.skeleton.channels
        if names is None:
            st.problem = (f"channel names unknown: the stream has {width} values; give --channels "
                          "(a model or motion file) or send a hello over PULL/SUB")
        elif self.skeleton is None:
            st.problem = "no skeleton (--skeleton-file)"
        else:
            try:
                st.cmap = self.skeleton.mapping(names)
                st.last_frame = self.skeleton.base.copy()
            except ValueError as e:
                st.problem = str(e)
        self.meta_version += 1

    def meta(self) -> dict[str, Any]:
        with self.lock:
            return self._meta()

    def _meta(self) -> dict[str, Any]:
        sk = self.skeleton
        out: dict[str, Any] = {"version": self.meta_version, "mode": self.mode, "source": self.source,
                               "rate": self.rate, "fps": self.fps, "max_dpr": self.max_dpr, "std_max": self.std_max, "error": self.error, "streams": []}
        if sk is not None:
            out["skeleton"] = {"joints": sk.joints, "parents": sk.parents, "source": sk.source}
        for sid in sorted(self.streams):
            st = self.streams[sid]
            n_styles = None if st.msg is None or st.msg.style is None else len(st.msg.style)
            out["streams"].append({"id": sid, "model": st.model, "problem": st.problem,
                                   "drawn": st.cmap is not None, "styles": n_styles,
                                   "joints_with_channels": (st.cmap.has_channels.tolist() if st.cmap else None)})
        return out

    def tick(self) -> dict[str, Any] | None:
        """One page update: the streams with a new frame since the last tick (None: nothing new)."""
        now = time.monotonic()
        with self.lock:
            for sid in [sid for sid, st in self.streams.items() if st.msg is not None and now - st.last_seen > FORGET_S]:
                del self.streams[sid]
                self.meta_version += 1
            fresh = [st for st in self.streams.values() if st.new and st.msg is not None]
            taken = []
            for st in fresh:
                taken.append((st, st.msg, st.tick_proc_ms, st.tick_age_ms))
                st.new, st.tick_proc_ms, st.tick_age_ms = False, None, None
                width = len(st.msg.angles)
                if (st.cmap is not None and st.cmap.width != width) or (st.problem and width != st.problem_width):
                    st.cmap, st.problem = None, ""  # a new hello the view did not see: look again
                self._resolve(st, width)
            stats = None
            if now >= self._next_stats:
                self._next_stats = now + STATS_EVERY_S
                stats = self._stats(now)
            version = self.meta_version
            # (the map and last pose as of now: a hello-ack may replace them while FK runs)
            drawn = [(st, m, st.cmap, st.last_frame) for st, m, _, _ in taken if st.cmap is not None]
        if not taken and stats is None:
            return None
        positions = self._positions(drawn)
        out_streams = []
        for st, m, proc, age in taken:
            d: dict[str, Any] = {"id": st.id, "seq": m.seq, "status": m.status, "gap": m.gap,
                                 "proc_ms": None if proc is None else round(proc, 3), "age_ms": None if age is None else round(age, 3),
                                 "filled": int(np.count_nonzero(m.filled))}
            if m.style is not None:
                d["style"] = [round(float(x), 4) for x in m.style]
            if m.phase is not None:
                d["phase"] = round(float(m.phase), 4)
            if st.id in positions:
                d["pos"], d["fill"] = positions[st.id]
            out_streams.append(d)
        upd: dict[str, Any] = {"meta_version": version, "time": time.time(), "streams": out_streams}
        if stats is not None:
            upd["stats"] = stats
        return upd

    def _positions(self, drawn: list[tuple[StreamState, wire.FillMsg, ChannelMap, np.ndarray]]
                   ) -> dict[str, tuple[list, list]]:
        if not drawn or self.skeleton is None:
            return {}
        rows = [cmap.frame(last, np.asarray(m.angles)) for _, m, cmap, last in drawn]
        P = np.asarray(self.skeleton.kin.positions(np.vstack(rows)))  # (n, J, 3) metres, one FK call a tick
        P = P @ self.skeleton.turn.T
        out = {}
        for (st, m, cmap, _), row, p in zip(drawn, rows, P):
            with self.lock:
                if st.cmap is cmap:
                    st.last_frame = row
            if not np.isfinite(p).all():
                continue  # not drawable; the page keeps the last good pose
            state = cmap.joint_state(np.asarray(m.filled, bool), np.asarray(m.std, np.float64))
            out[st.id] = (np.round(p, 3).reshape(-1).tolist(),  # millimetres: what a page can show
                          [round(float(x), 2) for x in state])
        return out

    def _stats(self, now: float) -> dict[str, Any]:
        res = {}
        for sid, st in self.streams.items():
            while st.recent and st.recent[0][0] < now - STATS_WINDOW_S:
                st.recent.popleft()
            if not st.recent:
                continue
            proc = np.array([r[1] for r in st.recent])
            ages = np.array([r[2] for r in st.recent if r[2] is not None])
            span = max(now - st.recent[0][0], 1e-3)
            d = {"hz": round(len(st.recent) / span, 1) if len(st.recent) > 1 else None,
                 "proc_p50_ms": round(float(np.percentile(proc, 50)), 3),
                 "proc_p99_ms": round(float(np.percentile(proc, 99)), 3), "frames": st.frames}
            if ages.size:
                d["age_p50_ms"] = round(float(np.percentile(ages, 50)), 3)
                d["age_p99_ms"] = round(float(np.percentile(ages, 99)), 3)
            res[sid] = d
        return res


def dumps(obj: Any) -> str:
    """JSON for the page: NaN and infinities (never meant to reach it) become null."""
    return json.dumps(obj, separators=(",", ":"), allow_nan=False, default=_default)


def _default(o: Any) -> Any:
    if isinstance(o, (np.floating, np.integer)):
        v = o.item()
        return None if isinstance(v, float) and not math.isfinite(v) else v
    raise TypeError(f"not JSON: {type(o).__name__}")
