"""`lacuna bridge | record | replay | bench | demo`."""
from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path
from typing import Any

from lacuna.errors import LacunaError

DEFAULT_ENDPOINT = "tcp://127.0.0.1:5555"


def _hostport(s: str) -> tuple[str, int]:
    host, sep, port = s.rpartition(":")
    if not sep or not port.isdigit():
        raise argparse.ArgumentTypeError(f"expected HOST:PORT (got {s!r})")
    return host or "127.0.0.1", int(port)


def _endpoint(s: str) -> str:
    return s if "://" in s else f"tcp://{s}"


def add_commands(cli: Any) -> None:
    p = cli.command("bridge", help="relay OSC frames from a capture system through the daemon and re-emit them filled")
    p.add_argument("--connect", type=_endpoint, default=DEFAULT_ENDPOINT, metavar="ADDR",
                   help=f"the daemon's ROUTER (default {DEFAULT_ENDPOINT})")
    p.add_argument("--listen", type=_hostport, default=("127.0.0.1", 9001), metavar="HOST:PORT",
                   help="receive the capture system's OSC here (default 127.0.0.1:9001)")
    p.add_argument("--send", type=_hostport, metavar="HOST:PORT", help="send filled frames as OSC bundles here")
    p.add_argument("--pub", metavar="ENDPOINT", help="also publish filled frames on a ZeroMQ PUB bound here")
    p.add_argument("--timeout-ms", type=float, default=20.0,
                   help="wait this long for the daemon before passing a frame through unfilled (default 20)")
    p.add_argument("--record", metavar="PATH", help="record raw+filled frames; {stream} in PATH becomes the stream id")
    p.set_defaults(func=_bridge)

    p = cli.command("record", help="save a live stream from the daemon's PUB output to a .lrec file")
    p.add_argument("--connect", type=_endpoint, required=True, metavar="ADDR", help="the daemon's PUB endpoint")
    p.add_argument("--stream", required=True, help="stream id to record")
    p.add_argument("--out", required=True, metavar="FILE.lrec")
    p.add_argument("--what", choices=["raw", "filled", "both"], default="both", help="what to keep (default both)")
    p.add_argument("--channels", metavar="NAMES", help="comma-separated channel names of the stream (for the file header)")
    p.add_argument("--fps", type=float, help="frame rate to note in the file (else estimated from timestamps)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--seconds", type=float, help="stop after this long")
    g.add_argument("--frames", type=int, help="stop after this many frames")
    p.add_argument("--quiet", "-q", action="store_true")
    p.set_defaults(func=_record)

    p = cli.command("replay", help="stream a recorded take to the daemon, write the filled take, report the error")
    p.add_argument("file", metavar="FILE", help="take to replay (.amc, .bvh, .csv or a .lrec recording)")
    p.add_argument("--connect", type=_endpoint, metavar="ADDR", help=f"the daemon's ROUTER (default {DEFAULT_ENDPOINT})")
    p.add_argument("--model", help="model name in the daemon's config (default: the daemon's choice)")
    p.add_argument("--serve", metavar="MODEL.npz", help="instead of --connect, start a daemon serving this model file")
    p.add_argument("--speed", type=float, default=1.0, help="times real time; 0 = as fast as the daemon answers (default 1)")
    p.add_argument("--drop", default="none", metavar="PATTERN",
                   help="erase values before sending: none, gaps[:GROUP,...], pan2009, taylor2007:right-leg|upper-body")
    p.add_argument("--seed", type=int, default=0, help="seed of the gaps pattern (default 0)")
    p.add_argument("--asf", help="ASF skeleton for an AMC take that has none beside it")
    p.add_argument("--out", metavar="FILE", help="filled take (default FILE's name + '.filled' in the current directory)")
    p.add_argument("--stream", default="replay", help="stream id (default replay)")
    p.add_argument("--json", dest="json_out", metavar="OUT")
    p.add_argument("--plot", metavar="OUT.png", help="truth vs fill on the most-erased channels")
    p.add_argument("--positions", action="store_true",
                   help="with --out FILE.csv: write joint positions (metres, forward kinematics) instead of angles")
    p.add_argument("--quiet", "-q", action="store_true")
    from mocap import skelmap

    skelmap.add_argument(p)
    p.set_defaults(func=_replay)

    p = cli.command("bench", help="latency of the daemon under N streams at R Hz (p50..max, drops, CPU)")
    p.add_argument("--streams", type=int, default=1)
    p.add_argument("--rate", type=float, default=120.0, help="frames per second per stream (default 120)")
    p.add_argument("--seconds", type=float, default=10.0)
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--model", metavar="FILE", help="start a daemon serving this model file")
    g.add_argument("--connect", metavar="ADDR", help="drive a running daemon at this ROUTER endpoint")
    p.add_argument("--model-name", help="with --connect: the model to use (default: the daemon's default)")
    p.add_argument("--floor", action="store_true", help="also run the same load against a pass-through filler")
    p.add_argument("--floor-model", default="floor", help="with --connect --floor: the daemon's pass-through model name")
    p.add_argument("--budget-ms", type=float, default=4.0, help="with --model: the daemon's per-frame budget (default 4)")
    p.add_argument("--overdue", choices=("drop", "serve"), default=None,
                   help="with --model: what the daemon does with a frame it cannot answer within its budget "
                        "(daemon.overdue; default drop)")
    p.add_argument("--busy-poll", type=float, default=0.0, metavar="MS",
                   help="spin instead of sleeping while waiting for answers (the client always; with --model the "
                        "daemon too, busy_poll_ms = MS), so neither side's kernel wake-up is in the round trip; "
                        "each spinning side uses a core (default 0: off)")
    p.add_argument("--connections", type=int, default=None, metavar="K",
                   help="DEALER sockets carrying the streams, stream i on socket i %% K (default: one per stream, "
                        "N separate plugins; 1 = one capture system multiplexing every performer)")
    p.add_argument("--cpu-latency", type=int, default=None, metavar="US",
                   help="with --model: the daemon holds a PM QoS CPU latency request of US microseconds "
                        "(daemon.cpu_latency_us; 0 keeps the CPUs out of sleep states) while it runs")
    p.add_argument("--realtime", type=int, default=None, metavar="PRIO",
                   help="with --model: the daemon's serving threads run SCHED_RR at this priority, 1-99 "
                        "(daemon.realtime_priority; needs CAP_SYS_NICE or RLIMIT_RTPRIO); the load generator "
                        "stays ordinary")
    p.add_argument("--prewarm", type=float, default=None, metavar="MS",
                   help="with --model: the daemon rehearses the last frame MS ms before the next is due, so the "
                        "frame finds its path warm (daemon.prewarm_ms; 0: off; default: the daemon's, 0.5)")
    p.add_argument("--bundle", action="store_true",
                   help="each connection sends its streams' frames of a tick as one `frames` message (answers come "
                        "back as one `replies`), as a capture system tracking several performers has them")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", dest="json_out", metavar="OUT")
    p.add_argument("--plot", metavar="OUT.png")
    p.add_argument("--quiet", "-q", action="store_true")
    p.set_defaults(func=_bench)

    p = cli.command("demo", help="train default and a small hlm, serve them beside hold, replay a held-out take of "
                                 "another performer with short and long dropouts, score against hold and offline "
                                 "interpolation")
    p.add_argument("--out", default="lacuna-demo", metavar="DIR", help="where models, plots and JSON go (default ./lacuna-demo)")
    p.add_argument("--source", choices=["auto", "data", "synthetic"], default="auto",
                   help="motion: auto (data dir, else fetch, else synthetic), data, synthetic")
    p.add_argument("--methods", help="comma-separated methods to train and serve beside hold (default: default,hlm; "
                                     "hlm and crbm get small settings; none = the baselines only)")
    p.add_argument("--take", metavar="NAME", help="the TEST take of mocap.splits to replay (default 02_01)")
    p.add_argument("--speed", type=float, default=1.0, help="replay speed, times real time (default 1)")
    p.add_argument("--budget-ms", type=float, default=8.0, help="the daemon's per-frame budget (default 8: one 120 Hz period)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", "-q", action="store_true")
    p.set_defaults(func=_demo)


def _stop_on_signals(flag_owner: Any) -> None:
    def handler(signum: int, frame: Any) -> None:  # only sets a flag the loop reads
        flag_owner.stop_flag = True

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)


def _bridge(args: argparse.Namespace) -> int:
    from clients.bridge import Bridge

    with Bridge(args.connect, args.listen, args.send, args.pub, timeout_s=args.timeout_ms / 1000.0,
                record=args.record) as b:
        _stop_on_signals(b)
        b.log(f"listening for OSC on {b.address[0]}:{b.address[1]}, daemon {args.connect}, "
              f"out {'OSC ' + ':'.join(map(str, args.send)) if args.send else ''} {args.pub or ''}".rstrip())
        b.serve_forever()
        c = b.counts
        b.log(f"stopped: {c.frames} frames, {c.filled} filled, {c.passed_through} passed through, "
              f"{c.dropped} dropped, {c.rejected} rejected")
    return 0


def _record(args: argparse.Namespace) -> int:
    from clients.record import record

    class Flag:
        stop_flag = False

    f = Flag()
    _stop_on_signals(f)
    ch = [c for c in args.channels.split(",") if c] if args.channels else None
    n = record(args.connect, args.stream, args.out, what=args.what, channels=ch, seconds=args.seconds,
               frames=args.frames, fps=args.fps, stop=lambda: f.stop_flag, progress=not args.quiet)
    print(f"recorded {n} frames of {args.stream} -> {args.out}")
    return 0 if n else 1


def _replay(args: argparse.Namespace) -> int:
    import numpy as np

    from clients import replay as rp
    from clients.harness import DaemonProcess
    from clients.takes import drop_mask, read_take, write_take

    if args.serve and args.connect:
        raise LacunaError("give --connect ADDR or --serve MODEL.npz, not both")
    motion, captured = read_take(args.file, args.asf)
    keep, bursts = drop_mask(args.drop, motion, args.seed, args.skeleton)
    known = np.isfinite(motion.frames) if captured is None else captured & np.isfinite(motion.frames)
    observed = keep & known
    p = Path(args.file)
    out = args.out or f"{p.stem}.filled{p.suffix}"
    if args.positions and (Path(out).suffix.lower() != ".csv" or motion.skeleton is None):
        raise LacunaError("--positions writes joint positions as CSV of a take with a skeleton (AMC, BVH): "
                          "give --out FILE.csv")
    if not args.quiet:
        print(f"replaying {args.file}: {motion.n_frames} frames x {len(motion.channels)} channels at {motion.fps:g} Hz, "
              f"drop {args.drop} ({int((known & ~keep).sum())} values erased)", file=sys.stderr)
    daemon = None
    try:
        if args.serve:
            _check_skeleton(args.serve, motion, args.skeleton)
            daemon = DaemonProcess({"model": args.serve}).start()
            endpoint = daemon.endpoint
        else:
            endpoint = args.connect or DEFAULT_ENDPOINT
        res = rp.replay(endpoint, motion, observed, speed=args.speed, stream=args.stream, model=args.model,
                        progress=not args.quiet)
    finally:
        if daemon is not None:
            daemon.stop()
    from mocap.motion import Motion

    filled = Motion(res.filled, list(motion.channels), motion.fps, motion.skeleton, out, dict(motion.meta))
    is_rec = p.suffix.lower() == ".lrec"
    kin = None
    if motion.skeleton is not None:
        from mocap.fk import Kinematics

        kin = Kinematics.from_motion(motion, skeleton=args.skeleton)
    if args.positions and kin is not None:
        from mocap.csvio import write_csv
        from mocap.fkerror import positions_motion

        write_csv(out, positions_motion(kin, res.filled, motion.fps, out))
    else:
        write_take(out, filled, args.asf, observed=observed if is_rec else None,
                   fills=rp.fill_messages(res, args.stream) if is_rec else None)
    summ = rp.summary(res, known)
    if kin is not None:
        from mocap.fkerror import joint_position_error

        summ["joint_positions"] = joint_position_error(kin, motion.frames, res.filled, known & ~observed)
    from mocap.metrics import cm_per_unit

    summ["figures"] = rp.figures(res, known, args.drop, cm_per_unit(motion.skeleton))
    summ["drop"] = args.drop
    summ["output"] = out
    acc, lat = summ["accuracy"], summ["latency"]
    rms = "-" if acc["rms_deg"] is None else f"{acc['rms_deg']:.2f}"
    print(f"filled take: {out}")
    hold = "" if acc.get("hold_rms_deg") is None else f" (holding the last value: {acc['hold_rms_deg']:.2f})"
    print(f"model {summ['model']}: RMS error on {acc['erased_angle_values']} erased angle values {rms} deg{hold}; "
          f"status {summ['status']}; dropped {summ['dropped']}; held {summ['held_values']} values")
    jp = summ.get("joint_positions")
    if jp and jp["n"]:
        print(f"joint positions of filled joints (forward kinematics): mean {jp['mean_cm']:.2f} cm, "
              f"p95 {jp['p95_cm']:.2f} cm, max {jp['max_cm']:.2f} cm over {jp['n']} joint-frames")
    fig = summ["figures"]
    if fig:
        print(_replay_figures(fig))
    if lat["p50_ms"] is not None:
        print(f"round trip ms: p50 {lat['p50_ms']:.3f}  p90 {lat['p90_ms']:.3f}  p99 {lat['p99_ms']:.3f}  "
              f"p99.9 {lat['p999_ms']:.3f}  max {lat['max_ms']:.3f}")
    if args.json_out:
        rp.write_json(args.json_out, summ)
        print(f"json: {args.json_out}")
    if args.plot:
        rp.plot_replay(args.plot, res, known, f"{p.name}: drop {args.drop}, {summ['model'] or 'fill'} with its 2-std band")
        print(f"plot: {args.plot}")
        if res.rtt_ms.size:
            lat_png = str(Path(args.plot).with_suffix("")) + ".latency.png"
            rp.plot_latency(lat_png, {summ["model"] or "fill": res.rtt_ms},
                            f"{p.name} at {args.speed:g}x: round trip, client send to answer read")
            print(f"latency histogram: {lat_png}")
    return 0


def _replay_figures(f: dict[str, Any]) -> str:
    """Two lines of ``clients.replay.figures``: what a technician weighs before trusting the fills."""
    def num(v: Any, spec: str = ".2f") -> str:
        return "n/a" if v is None else format(v, spec)

    lines = [f"first dropped frame: median error {num(f['onset_err_median_deg'])} deg (the performer's own step "
             f"{num(f['onset_truth_step_median_deg'])}); first 100 ms: {num(f['rms_first_100ms_deg'])} deg "
             f"(holding: {num(f['hold_rms_first_100ms_deg'])}); gaps 0.1-0.25 s {num(f['rms_short_deg'])}, "
             f"0.5-2 s {num(f['rms_long_deg'])} deg"]
    pops = "n/a" if f["pop_over_2deg"] is None else f"{100 * f['pop_over_2deg']:.2f}%"
    lines.append(f"confidence: {num(f['within_2std'], '.3f')} of dropped values within 2 reported std (0.95 is "
                 f"calibrated; n/a: no std reported), NLL {num(f['nll_per_value'])} per value; steps over 2 deg "
                 f"beyond the performer's own: {pops} (largest {num(f['pop_max_deg'], '.1f')} deg)")
    return "\n".join(lines)


def _bench(args: argparse.Namespace) -> int:
    from clients import bench

    if args.streams < 1 or args.rate <= 0 or args.seconds <= 0:
        raise LacunaError(f"--streams >= 1, --rate > 0 and --seconds > 0 please "
                          f"(got {args.streams}, {args.rate}, {args.seconds})")
    if args.connections is not None and not 1 <= args.connections <= args.streams:
        raise LacunaError(f"--connections must be between 1 and --streams ({args.streams}), got {args.connections}")
    if args.cpu_latency is not None and not args.model:
        raise LacunaError("--cpu-latency sets the config of the daemon --model starts; a daemon at --connect "
                          "takes it from its own config (daemon.cpu_latency_us)")
    for flag, v in (("--realtime", args.realtime), ("--overdue", args.overdue), ("--prewarm", args.prewarm)):
        if v is not None and not args.model:
            raise LacunaError(f"{flag} sets the config of the daemon --model starts; a daemon at --connect "
                              f"takes it from its own config")
    if args.realtime is not None and not 1 <= args.realtime <= 99:
        raise LacunaError(f"--realtime must be a priority between 1 and 99 (got {args.realtime})")
    if args.realtime is not None and args.busy_poll:
        raise LacunaError("--realtime and --busy-poll cannot be used together: a spinning real-time thread starves "
                          "the kernel's network processing on its core")
    if args.prewarm is not None and not 0 <= args.prewarm <= 100:
        raise LacunaError(f"--prewarm must be between 0 and 100 ms (got {args.prewarm})")
    if args.cpu_latency is not None and not 0 <= args.cpu_latency <= 1_000_000:
        raise LacunaError(f"--cpu-latency must be between 0 and 1000000 microseconds (got {args.cpu_latency})")
    return bench.run(args)


def _demo(args: argparse.Namespace) -> int:
    """SIGTERM (a ``kill``, a CI job's timeout) stops the demo as Ctrl-C does: it unwinds through the
    demo's ``finally``, which stops the daemon it started (the default SIGTERM would end this process
    at once and leave that daemon running, orphaned)."""
    from clients import demo

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    before = signal.signal(signal.SIGTERM, interrupt)
    try:
        return demo.run(args)
    finally:
        signal.signal(signal.SIGTERM, before)


def _check_skeleton(model_path: str, motion: Any, skeleton: str | None) -> None:
    """A model of another skeleton than the take's: a clear error before any daemon starts."""
    from lacuna import modelfile
    from mocap import skelmap

    try:
        meta, _ = modelfile.load_arrays(model_path)
    except (OSError, modelfile.ModelFileError):
        return  # the daemon reports an unreadable model file itself
    ch = meta.get("channels")
    if isinstance(ch, list):
        why = skelmap.mismatch(ch, motion.channels, motion.source, skeleton, str(meta.get("skeleton_map") or ""))
        if why:
            raise LacunaError(f"{model_path}: {why}")
