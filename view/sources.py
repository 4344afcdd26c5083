"""Where the view's frames come from: the daemon's PUB output, or a file played back.

Both run in a thread of their own and hand every frame to :meth:`view.feed.Feed.on_fill`, which
only keeps it (newest wins): neither ever waits for the page.

The subscriber is one more SUB on the daemon's PUB socket, as ``lacuna record`` is: the daemon
sends to it as to any subscriber and drops what a slow one does not take (ZeroMQ's high-water
mark), so the view cannot slow the daemon down.  ZeroMQ prefix-matches topics (``s1`` also
matches ``s10``): with ``streams`` given, the topic frame is compared exactly.
"""
from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator

import numpy as np
import zmq

from daemon import wire
from view.feed import Feed

POLL_MS = 200  # how often the subscriber looks at its stop flag
MAX_BYTES = 1 << 24


class Subscriber(threading.Thread):
    """Feed every ``fill`` and ``hello-ack`` published on ``endpoint`` to ``feed``."""

    def __init__(self, endpoint: str, feed: Feed, streams: list[str] | None = None):
        super().__init__(name="view-sub", daemon=True)
        self.endpoint, self.feed = endpoint, feed
        self.topics = {s.encode() for s in streams} if streams else None
        self.stop_event = threading.Event()
        self.ready = threading.Event()
        self.undecodable = 0
        self.error: BaseException | None = None

    def run(self) -> None:
        ctx = zmq.Context()
        sub = ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.LINGER, 0)
        try:
            for t in self.topics or {b""}:
                sub.setsockopt(zmq.SUBSCRIBE, t)
            sub.connect(self.endpoint)
            self.ready.set()
            while not self.stop_event.is_set():
                if not sub.poll(POLL_MS, zmq.POLLIN):
                    continue
                while True:  # everything waiting, then poll again
                    try:
                        parts = sub.recv_multipart(zmq.NOBLOCK)
                    except zmq.Again:
                        break
                    self._handle(parts)
        except BaseException as e:  # the page shows that the feed died, and why
            self.error = e
            self.feed.fail(f"subscriber: {type(e).__name__}: {e}")
        finally:
            self.ready.set()
            sub.close(0)
            ctx.term()

    def _handle(self, parts: list[bytes]) -> None:
        if len(parts) != 2 or (self.topics is not None and parts[0] not in self.topics):
            return
        try:
            msg = wire.decode(parts[1], MAX_BYTES)
        except wire.WireError:
            self.undecodable += 1
            return
        if isinstance(msg, wire.FillMsg):
            self.feed.on_fill(msg)
        elif isinstance(msg, wire.HelloAck):
            self.feed.on_ack(msg)

    def stop(self) -> None:
        self.stop_event.set()


def file_frames(path: str, asf: str | None = None) -> tuple[str, list[str], float, Iterator[wire.FillMsg], int]:
    """A file as the fills the view would have seen: (stream id, channels, fps, frames, count).

    ``.lrec``: the daemon's fills where they were recorded, else the raw frames (nothing filled).
    A motion file (``.amc``/``.bvh``/``.csv``): every value observed.
    """
    stem = os.path.splitext(os.path.basename(path))[0]
    if path.lower().endswith(".lrec"):
        from clients.recording import read_recording

        R = read_recording(path)
        fps = float(R.fps or _fps(R.t))
        sid = R.stream or stem
        T, C = R.raw.shape
        zero = np.zeros(C, np.float32)

        def gen_rec() -> Iterator[wire.FillMsg]:
            for k in range(T):
                if R.filled_angles is not None and R.status[k]:
                    assert R.filled is not None and R.std is not None
                    yield wire.FillMsg(sid, int(R.seq[k]), float(R.t[k]), R.filled_angles[k].astype(np.float32),
                                       R.filled[k], R.std[k].astype(np.float32), R.status[k], "recorded", 0)
                else:
                    yield wire.FillMsg(sid, int(R.seq[k]), float(R.t[k]), R.raw[k].astype(np.float32),
                                       np.zeros(C, bool), zero, "raw", "recorded", 0)
        return sid, list(R.channels), fps, gen_rec(), T
    from mocap.io import read_motion

    m = read_motion(path, asf)
    C = len(m.channels)
    zero = np.zeros(C, np.float32)

    def gen_motion() -> Iterator[wire.FillMsg]:
        for k in range(m.n_frames):
            yield wire.FillMsg(stem, k, k / m.fps, m.frames[k].astype(np.float32), np.zeros(C, bool), zero,
                               "raw", "file", 0)
    return stem, list(m.channels), float(m.fps), gen_motion(), m.n_frames


def _fps(t: np.ndarray) -> float:
    d = np.diff(t)
    d = d[d > 0]
    return float(1.0 / np.median(d)) if d.size else 120.0


class Player(threading.Thread):
    """Play a file into ``feed`` at its frame rate times ``speed`` (absolute deadlines), once or looped."""

    def __init__(self, path: str, feed: Feed, speed: float = 1.0, loop: bool = False, asf: str | None = None):
        super().__init__(name="view-play", daemon=True)
        if speed <= 0:
            raise ValueError(f"--speed must be > 0 (got {speed})")
        self.path, self.feed, self.speed, self.loop, self.asf = path, feed, speed, loop, asf
        # read now, so a bad file is an error at start; the first pass plays these frames
        self.stream, self.channels, self.fps, self._frames, self.n_frames = file_frames(path, asf)
        self.stop_event = threading.Event()
        self.played = 0
        self.done = threading.Event()

    def run(self) -> None:
        try:
            frames = self._frames
            while not self.stop_event.is_set():
                period = 1.0 / (self.fps * self.speed)
                t0 = time.monotonic()
                for k, msg in enumerate(frames):
                    if self.stop_event.wait(max(0.0, t0 + k * period - time.monotonic())):
                        return
                    self.feed.on_fill(msg, latency=False)
                    self.played += 1
                if not self.loop:
                    return
                frames = file_frames(self.path, self.asf)[3]
        except BaseException as e:
            self.feed.fail(f"player: {type(e).__name__}: {e}")
        finally:
            self.done.set()

    def stop(self) -> None:
        self.stop_event.set()
