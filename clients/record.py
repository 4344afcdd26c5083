"""``lacuna record``: save a live stream from the daemon's PUB output to a recording file.

Every ``fill`` the daemon publishes carries the frame as captured (observed values are echoed
exactly, to float32) and the filled values with their mask, so one subscription gives both the
raw take (values not marked filled; NaN where the capture had nothing) and the filled one.
``--what raw`` keeps only the first, ``filled`` only the second, ``both`` (default) both.
The file is read by ``lacuna replay`` (clients/recording.py).

ZeroMQ prefix-matches topics (``s1`` also matches ``s10``), so the topic frame is compared
exactly here.
"""
from __future__ import annotations

import sys
import time
from collections.abc import Callable

import numpy as np
import zmq

from clients.recording import RecordingWriter
from daemon import wire

POLL_MS = 200  # wake up this often to look at the stop flag and the time limit
PROGRESS_EVERY_S = 2.0


def record(pub_endpoint: str, stream: str, path: str, *, what: str = "both", channels: list[str] | None = None,
           seconds: float | None = None, frames: int | None = None, fps: float | None = None,
           stop: Callable[[], bool] = lambda: False, progress: bool = True,
           ready: Callable[[], None] | None = None) -> int:
    """Record one stream until ``seconds``/``frames`` is reached or ``stop()`` says so; returns
    the number of frames written."""
    if what not in ("raw", "filled", "both"):
        raise ValueError(f"--what must be raw, filled or both (got {what!r})")
    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.SUBSCRIBE, stream.encode())
    sub.connect(pub_endpoint)
    writer: RecordingWriter | None = None
    topic = stream.encode()
    end = None if seconds is None else time.monotonic() + seconds
    next_report = time.monotonic() + PROGRESS_EVERY_S
    if ready:
        ready()
    try:
        while not stop():
            if end is not None and time.monotonic() >= end:
                break
            if frames is not None and writer is not None and writer.n_frames >= frames:
                break
            if not sub.poll(POLL_MS, zmq.POLLIN):
                continue
            parts = sub.recv_multipart()
            if len(parts) != 2 or parts[0] != topic:
                continue
            try:
                msg = wire.decode(parts[1], max_bytes=1 << 24)
            except wire.WireError:
                continue
            if not isinstance(msg, wire.FillMsg):
                continue
            if writer is None:
                C = len(msg.angles)
                names = list(channels) if channels else [f"ch{i}" for i in range(C)]
                if len(names) != C:
                    raise ValueError(f"--channels lists {len(names)} names, stream {stream!r} has {C} values")
                writer = RecordingWriter(path, names, fps, stream, f"lacuna record {pub_endpoint}")
            a = np.asarray(msg.angles, dtype=np.float64)
            raw_obs = ~np.asarray(msg.filled, bool) & np.isfinite(a)
            writer.write(msg.seq, msg.t,
                         None if what == "filled" else a, None if what == "filled" else raw_obs,
                         None if what == "raw" else msg)
            if progress and time.monotonic() >= next_report:
                next_report += PROGRESS_EVERY_S
                print(f"\r  record {stream}: {writer.n_frames} frames", end="", file=sys.stderr, flush=True)
    finally:
        n = writer.n_frames if writer else 0
        if writer:
            writer.close()
        sub.close(linger=0)
        ctx.term()
        if progress:
            print(f"\r  record {stream}: {n} frames -> {path}", file=sys.stderr, flush=True)
    return n
