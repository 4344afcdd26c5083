"""``lacuna bench``: latency of the daemon under a given load, beside its transport floor.

    lacuna bench --streams 64 --rate 120 --seconds 10 --model hlm.npz --floor --json out.json --plot out.png

With ``--model FILE`` it starts its own daemon (a real ``lacuna serve`` subprocess on a free
loopback port) serving that file and a pass-through filler on the same channels; with
``--connect ADDR`` it drives a running daemon (``--model-name`` picks the model, ``--floor-model``
the pass-through one).  Each run's counts are checked against the daemon's own ``status``.
CPU use of the daemon comes from /proc/<pid>/stat (utime + stime over the run's wall time, as
a percentage of one core).
"""
from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np

from clients import loadgen
from clients.control import control
from clients.harness import DaemonProcess, cpu_seconds, rss_bytes
from lacuna.errors import LacunaError

FLOOR_MODEL = "floor"


def bench_take(channels: list[str], seed: int = 0) -> tuple[np.ndarray, np.ndarray, str]:
    """Frames (T, C) and a gaps-protocol mask (T, C) on ``channels``, and where they came from.

    Real CMU 07_01 when the data directory has it and the channels are CMU's; else the
    synthetic gait; else (foreign channel names) smooth random curves.
    """
    from clients import synth
    from clients.takes import drop_mask
    from mocap.motion import Motion

    frames = None
    src = ""
    if set(channels) <= set(synth.CMU_CHANNELS):
        try:
            from mocap.datasets import load_trial

            m = load_trial("07_01")
            frames, src = m.frames[:, m.index(channels)], "CMU 07_01"
        except (LacunaError, OSError, KeyError):
            g = synth.gait(6.0, seed)
            frames, src = g.frames[:, g.index(channels)], "synthetic gait"
    if frames is None:
        rng = np.random.default_rng(seed)
        t = np.arange(720)[:, None] / 120.0
        frames = 20 * np.sin(2 * np.pi * t / 1.1 + rng.uniform(0, 6, len(channels)))
        src = "random sinusoids"
    mot = Motion(frames, list(channels), 120.0, None, "bench")
    obs, _ = drop_mask("gaps", mot, seed)
    return frames, obs, src


def _daemon_counts(status: dict[str, Any], prefix: str) -> dict[str, int]:
    out = {"frames_in": 0, "served": 0, "degraded": 0, "dropped": 0, "rejected": 0, "over_budget": 0}
    for sid, s in (status.get("streams") or {}).items():
        if sid.startswith(prefix + "-"):
            out["frames_in"] += int(s.get("frames_in", 0))
            out["served"] += int(s.get("frames_out", 0))
            out["degraded"] += int(s.get("degraded", 0))
            out["dropped"] += int(s.get("dropped", 0))
            out["rejected"] += int(s.get("rejected", 0))
            out["over_budget"] += int(s.get("over_budget", 0))
    return out


def run_one(endpoint: str, channels: list[str], frames: np.ndarray, observed: np.ndarray, *, streams: int,
            rate: float, seconds: float, model: str | None, prefix: str, pid: int | None,
            progress: bool = True, busy: bool = False, connections: int | None = None,
            bundle: bool = False) -> tuple[dict[str, Any], np.ndarray]:
    """One load run; returns (JSON-ready row, round trips in ms)."""
    cpu0 = cpu_seconds(pid) if pid else None
    rss0 = rss_bytes(pid) if pid else None
    w0 = time.perf_counter()
    res = loadgen.run_load(endpoint, channels, frames, observed, n_streams=streams, rate=rate, seconds=seconds,
                           model=model, prefix=prefix, progress=progress, busy=busy, connections=connections,
                           bundle=bundle)
    wall = time.perf_counter() - w0
    cpu1 = cpu_seconds(pid) if pid else None
    rss1 = rss_bytes(pid) if pid else None
    st = control(endpoint, "status", timeout_s=5.0).result
    dc = _daemon_counts(st, prefix)
    row: dict[str, Any] = {
        "model": model or st.get("default_model"), "streams": streams, "rate_hz": rate, "seconds": seconds,
        "connections": streams if connections is None else connections, "bundle": bundle,
        **loadgen.percentiles(res.rtt_ms),
        "served": res.served, "degraded": res.degraded, "dropped": res.dropped, "passthrough": res.passthrough,
        "errors": res.errors, "lost": res.lost, "sent": res.sent, "unsent": res.unsent,
        "offered": streams * max(1, int(round(seconds * rate))),
        "drop_reasons": res.drop_reasons, "error_reasons": res.error_reasons,
        "cpu_percent": None if cpu0 is None or cpu1 is None else 100.0 * (cpu1 - cpu0) / wall,
        "daemon_rss_mb": None if rss1 is None else rss1 / 2**20,
        "daemon_rss_growth_mb": None if rss0 is None or rss1 is None else (rss1 - rss0) / 2**20,
        "daemon_proc_ms_p50": float(np.median(res.proc_us) / 1000.0) if res.proc_us.size else None,
        "daemon_proc_ms_p99": float(np.percentile(res.proc_us, 99) / 1000.0) if res.proc_us.size else None,
        # the share of served frames whose receipt-to-sent overran the daemon's per-frame budget
        # (the daemon's own count: the proc_us in a fill stops at its encoding, before the send)
        "daemon_over_budget_pct": float(100.0 * dc["over_budget"] / dc["served"]) if dc["served"] else None,
        "daemon_overdue": int(res.drop_reasons.get("overdue", 0)),
        # the same from each fill's proc_us (receipt to its encoding, before the tick's sends)
        "daemon_proc_over_budget_pct": (float(100.0 * np.mean(res.proc_us > 1000.0 * float(st["budget_ms"])))
                                        if res.proc_us.size and st.get("budget_ms") else None),
        "send_lateness_ms_p99": float(np.percentile(res.lateness_ms, 99)),
        "daemon_counts": dc, "cpu_latency": st.get("cpu_latency"), "realtime": st.get("realtime"),
        "prewarm": st.get("prewarm"),
        "counts_agree": dc["served"] == res.served and dc["dropped"] == res.dropped and dc["degraded"] == res.degraded,
    }
    return row, res.rtt_ms


def run(args: Any) -> int:
    from clients.replay import plot_latency, write_json

    progress = not args.quiet
    daemon: DaemonProcess | None = None
    try:
        if args.model:
            from lacuna.modelfile import load_arrays

            meta, _ = load_arrays(args.model)
            channels = list(meta["channels"])
            daemon = DaemonProcess({"bench": args.model, FLOOR_MODEL: {"builtin": "passthrough", "channels": channels}},
                                   "bench", daemon={"budget_ms": float(args.budget_ms),
                                                    **({"overdue": args.overdue} if args.overdue else {}),
                                                    **({"realtime_priority": args.realtime} if args.realtime else {}),
                                                    **({"busy_poll_ms": float(args.busy_poll)} if args.busy_poll else {}),
                                                    **({"prewarm_ms": float(args.prewarm)} if args.prewarm is not None else {}),
                                                    **({"cpu_latency_us": args.cpu_latency} if args.cpu_latency is not None else {})})
            if progress:
                print(f"starting the daemon on {daemon.endpoint} with {args.model} ...", file=sys.stderr, flush=True)
            daemon.start()
            pid: int | None
            model_name: str | None
            endpoint, pid, model_name, floor_name = daemon.endpoint, daemon.pid, "bench", FLOOR_MODEL
        else:
            endpoint = args.connect if "://" in args.connect else f"tcp://{args.connect}"
            st = control(endpoint, "status", timeout_s=5.0).result
            models = st.get("models") or {}
            model_name = args.model_name or st.get("default_model")
            if model_name not in models:
                raise LacunaError(f"the daemon at {endpoint} has no model {model_name!r} (has: {', '.join(models)})")
            floor_name = args.floor_model
            if args.floor and floor_name not in models:
                raise LacunaError(f"--floor needs a pass-through model {floor_name!r} in the daemon at {endpoint} "
                                  f"(has: {', '.join(models)}); add [models.{floor_name}] builtin = \"passthrough\"")
            channels = _model_channels(models[model_name], endpoint, str(model_name))
            # CPU is read from /proc only when the daemon is on this machine
            pid = st.get("pid") if endpoint.startswith(("tcp://127.", "tcp://localhost", "ipc://")) else None
        frames, observed, src = bench_take(channels, args.seed)
        if progress:
            print(f"load: {args.streams} streams x {args.rate:g} Hz x {args.seconds:g} s of {src} "
                  f"({len(channels)} channels, gaps-protocol dropouts)", file=sys.stderr, flush=True)
        runs: dict[str, dict[str, Any]] = {}
        rtts: dict[str, np.ndarray] = {}
        todo = [("model", model_name)] + ([("floor", floor_name)] if args.floor else [])
        for label, name in todo:
            if progress:
                print(f"run {label}: model {name}", file=sys.stderr, flush=True)
            prefix = f"bench{int(time.time() * 1000) % 10**8}-{label}"
            runs[label], rtts[label] = run_one(endpoint, channels, frames, observed, streams=args.streams,
                                               rate=args.rate, seconds=args.seconds, model=name, prefix=prefix,
                                               pid=pid, progress=progress, busy=args.busy_poll > 0,
                                               connections=args.connections, bundle=args.bundle)
    finally:
        if daemon is not None:
            daemon.stop()
    print(format_table(runs))
    out = {**runs["model"], "runs": runs, "take": src, "endpoint": endpoint,
           "started_daemon": bool(args.model), "budget_ms": args.budget_ms if args.model else None,
           "overdue": (args.overdue or "drop") if args.model else None,
           "busy_poll_ms": args.busy_poll}
    if args.json_out:
        write_json(args.json_out, out)
        print(f"json: {args.json_out}")
    if args.plot:
        plot_latency(args.plot, {f"{k} ({runs[k]['model']})": v for k, v in rtts.items()},
                     f"{args.streams} streams x {args.rate:g} Hz, {args.seconds:g} s")
        print(f"plot: {args.plot}")
    bad = [k for k, r in runs.items() if not r["counts_agree"]]
    if bad:
        print(f"lacuna: warning: bench counts differ from the daemon's status for run(s) {bad}: "
              + "; ".join(f"{k}: bench served/dropped/degraded {runs[k]['served']}/{runs[k]['dropped']}/{runs[k]['degraded']}"
                          f" vs daemon {runs[k]['daemon_counts']}" for k in bad), file=sys.stderr)
    return 0


def _model_channels(info: dict[str, Any], endpoint: str, name: str) -> list[str]:
    ch = info.get("channel_names") or info.get("channels_list")
    if isinstance(ch, list) and ch:
        return list(ch)
    f = info.get("file")
    if f:
        from lacuna.modelfile import load_arrays

        return list(load_arrays(f)[0]["channels"])
    raise LacunaError(f"cannot learn the channel names of model {name!r} at {endpoint} (no file in its status)")


def format_table(runs: dict[str, dict[str, Any]]) -> str:
    head = (f"{'run':<6} {'model':<10} {'streams':>7} {'conns':>5} {'Hz':>5} {'p50':>7} {'p90':>7} {'p99':>7} {'p99.9':>7} {'max':>7}"
            f" {'served':>8} {'degraded':>8} {'dropped':>8} {'overdue':>8} {'late%':>6} {'cpu%':>6}")
    lines = [head, "-" * len(head)]
    for k, r in runs.items():

        def f(v: float | None) -> str:
            return "   -   " if v is None else f"{v:7.3f}"

        cpu = "  -" if r["cpu_percent"] is None else f"{r['cpu_percent']:6.1f}"
        late = r.get("daemon_over_budget_pct")
        late_s = f"{'-':>6}" if late is None else f"{late:6.1f}"
        lines.append(f"{k:<6} {str(r['model'])[:10]:<10} {r['streams']:>7} {str(r.get('connections', r['streams'])) + ('b' if r.get('bundle') else ''):>5} {r['rate_hz']:>5g} {f(r['p50_ms'])} {f(r['p90_ms'])}"
                     f" {f(r['p99_ms'])} {f(r['p999_ms'])} {f(r['max_ms'])} {r['served']:>8} {r['degraded']:>8}"
                     f" {r['dropped']:>8} {r.get('daemon_overdue', 0):>8} {late_s} {cpu}")
    lines.append("(round trips in ms over ZeroMQ DEALER->ROUTER on loopback; dropped includes overdue = frames the daemon"
                 " dropped because it could not answer them within its budget; late% = served frames whose receipt-to-sent"
                 " overran the daemon's budget; cpu% = daemon process, % of one core;"
                 " conns 'b' = one `frames` bundle per connection and tick)")
    return "\n".join(lines)
