"""``lacuna view``: serve the live page (its own process, one more subscriber of the daemon's PUB)."""
from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from typing import Any

from lacuna.errors import LacunaError
from view import PAGE_FPS, PAGE_MAX_DPR

DEFAULT_LISTEN = "127.0.0.1:8765"


def add_commands(cli: Any) -> None:
    p = cli.command("view", help="a live web page of every stream: skeletons coloured by confidence, style, "
                                 "gait phase, latency; or a recording played back")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--connect", metavar="PUB", help="the daemon's PUB endpoint ([zmq] pub), e.g. tcp://127.0.0.1:5556")
    src.add_argument("--play", metavar="FILE", help="play a .lrec recording (or a .amc/.bvh/.csv take) instead")
    p.add_argument("--speed", type=float, default=1.0, help="with --play: times the recorded rate (default 1)")
    p.add_argument("--loop", action="store_true", help="with --play: start again at the end")
    p.add_argument("--skeleton-file", metavar="FILE",
                   help="the performers' skeleton: a .asf, .amc or .bvh file (a played .amc/.bvh is its own)")
    p.add_argument("--asf", metavar="ASF", help="the ASF of an .amc given to --skeleton-file or --play")
    p.add_argument("--channels", metavar="FILE",
                   help="the streams' channel names, from a model (.npz), a recording (.lrec) or a take; "
                        "default: the stream's hello-ack on the PUB, else the skeleton file's own channels")
    p.add_argument("--stream", action="append", metavar="ID", help="show only this stream (repeatable)")
    p.add_argument("--listen", default=DEFAULT_LISTEN, metavar="HOST:PORT",
                   help=f"where the page is served (default {DEFAULT_LISTEN}; port 0 picks a free one)")
    p.add_argument("--rate", type=float, default=None, metavar="HZ",
                   help="page updates a second, each with every stream's newest frame (default: --fps)")
    p.add_argument("--fps", type=float, default=PAGE_FPS, metavar="N",
                   help=f"the page draws at most N frames a second, and only when a new one came (default "
                        f"{PAGE_FPS:g}; 60 on a machine with CPU to spare); a page's ?fps=N overrides it")
    p.add_argument("--max-dpr", type=float, default=PAGE_MAX_DPR, metavar="R",
                   help=f"draw at most R device pixels per CSS pixel (default {PAGE_MAX_DPR:g}; 2 for sharp "
                        "lines on a 2x screen, at 4x the raster cost); a page's ?dpr=R overrides it")
    p.add_argument("--std-max", type=float, default=20.0, metavar="DEG",
                   help="the std (degrees) at the top of the confidence colour scale (default 20)")
    p.add_argument("--nice", type=int, default=10, metavar="N",
                   help="lower the view's CPU priority by N (default 10), so it yields to the daemon and the "
                        "capture software on a shared machine; 0 keeps it. A browser on the capture box "
                        "takes CPU from the daemon too: run the daemon (daemon.realtime_priority) and the capture "
                        "software real-time there and the browser ordinary (docs/CLIENTS.md)")
    p.add_argument("--seconds", type=float, metavar="S", help="exit after S seconds (default: until Ctrl-C)")
    p.set_defaults(func=run)


def _listen(s: str) -> tuple[str, int]:
    host, sep, port = s.rpartition(":")
    if not sep or not port.isdigit():
        raise LacunaError(f"--listen expects HOST:PORT (got {s!r})")
    return host or "127.0.0.1", int(port)


def _renice(n: int) -> None:
    """Lower every thread's priority by ``n`` (Linux nice is per thread: threads a library started
    at import keep theirs otherwise); threads started later inherit the main thread's."""
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        tids = [0]
    try:
        for tid in tids:
            os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + n)
    except OSError as e:  # (a lower priority is always allowed; this is for a negative N)
        raise LacunaError(f"--nice {n}: {e.strerror}") from None


def load_skeleton_motion(path: str, asf: str | None = None):
    """The motion file (or bare ASF) whose skeleton the streams are drawn on."""
    from mocap.motion import Motion

    if not os.path.exists(path):
        raise LacunaError(f"--skeleton-file {path}: no such file")
    if path.lower().endswith(".asf"):
        import numpy as np

        from mocap.asf import read_asf

        sk = read_asf(path)
        return Motion(np.zeros((0, len(sk.channels))), list(sk.channels), 120.0, sk, path)
    from mocap.io import read_motion

    return read_motion(path, asf)


def channel_names(path: str) -> list[str]:
    """Channel names from a model file, a recording or a motion file."""
    if not os.path.exists(path):
        raise LacunaError(f"--channels {path}: no such file")
    low = path.lower()
    if low.endswith(".npz"):
        from lacuna import modelfile

        meta, _ = modelfile.load_arrays(path)
        ch = meta.get("channels")
        if not isinstance(ch, list) or not ch:
            raise LacunaError(f"--channels {path}: the model file lists no channels")
        return [str(c) for c in ch]
    if low.endswith(".lrec"):
        from clients.recording import read_recording

        return list(read_recording(path).channels)
    if low.endswith(".asf"):
        from mocap.asf import read_asf

        return list(read_asf(path).channels)
    from mocap.io import read_motion

    return list(read_motion(path).channels)


def run(args: argparse.Namespace) -> int:
    from view.feed import Feed, Skeleton
    from view.server import ViewServer
    from view.sources import Player, Subscriber

    host, port = _listen(args.listen)
    if args.rate is None:
        args.rate = args.fps
    if args.fps <= 0 or args.max_dpr <= 0:
        raise LacunaError(f"--fps and --max-dpr must be > 0 (got {args.fps:g}, {args.max_dpr:g})")
    if args.connect and (args.loop or args.speed != 1.0):
        raise LacunaError("--speed and --loop apply to --play")
    if args.nice:
        _renice(args.nice)
    if args.play and not os.path.exists(args.play):
        raise LacunaError(f"--play {args.play}: no such file")
    skel_path = args.skeleton_file
    if skel_path is None and args.play and not args.play.lower().endswith((".lrec", ".csv")):
        skel_path = args.play  # an .amc/.bvh carries its skeleton
    skeleton = None
    if skel_path is None and args.channels and args.channels.lower().endswith(".npz") and os.path.exists(args.channels):
        try:
            skeleton = Skeleton.from_model(args.channels)  # a model trained from takes carries theirs
        except (ValueError, KeyError) as e:
            raise LacunaError(f"--channels {args.channels}: its skeleton: {e}") from None
        skel_path = skeleton.source if skeleton else None
    if skel_path is None:
        raise LacunaError("--skeleton-file is needed to draw the skeletons (a .asf, .amc or .bvh of the performers; "
                          "or --channels a model file trained from takes, which carries their skeleton)")
    if skeleton is None:
        try:
            skeleton = Skeleton.from_motion(load_skeleton_motion(skel_path, args.asf))
        except (ValueError, KeyError) as e:
            raise LacunaError(f"--skeleton-file {skel_path}: {e}") from None
    channels = channel_names(args.channels) if args.channels else None
    source: Any
    if args.play:
        feed = Feed(skeleton, channels, rate=args.rate, std_max=args.std_max, mode="play", source=args.play,
                    fps=args.fps, max_dpr=args.max_dpr)
        source = Player(args.play, feed, args.speed, args.loop, args.asf if args.play.lower().endswith(".amc") else None)
        if channels is None:
            feed.default_channels = source.channels
        what = f"playing {args.play} ({source.n_frames} frames at {source.fps:g} Hz x {args.speed:g})"
    else:
        feed = Feed(skeleton, channels, rate=args.rate, std_max=args.std_max, mode="live", source=args.connect,
                    fps=args.fps, max_dpr=args.max_dpr)
        endpoint = args.connect if "://" in args.connect else f"tcp://{args.connect}"
        source = Subscriber(endpoint, feed, args.stream)
        what = f"subscribed to {endpoint}"
    try:
        server = ViewServer(feed, host, port).start()
    except OSError as e:
        raise LacunaError(f"--listen {args.listen}: {e.strerror or e}") from None
    stop = threading.Event()

    def handler(signum: int, frame: Any) -> None:  # only sets the flag the main thread waits on
        stop.set()

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)
    source.start()
    if host not in ("127.0.0.1", "localhost", "::1"):
        print(f"lacuna view: warning: serving on {host} without authentication: anyone who can reach it "
              "sees the streams", file=sys.stderr, flush=True)
    print(f"lacuna view: {server.url} ({what}, skeleton {skel_path}, {args.rate:g} updates/s, drawn at most {args.fps:g} fps)", flush=True)
    try:
        stop.wait(args.seconds)
    finally:
        source.stop()
        server.stop()
        source.join(5)
    if feed.error:
        print(f"lacuna: error: {feed.error}", file=sys.stderr)
        return 2
    return 0
