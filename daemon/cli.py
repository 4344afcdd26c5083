"""`lacuna serve` and `lacuna status`."""
from __future__ import annotations

import argparse
import json
import sys
from typing import Any

DEFAULT_ENDPOINT = "tcp://127.0.0.1:5555"


def add_commands(cli: Any) -> None:
    p = cli.command("serve", help="run the gap-filling daemon (ZeroMQ + OSC)")
    p.add_argument("--config", required=True, metavar="FILE", help="TOML config (see systemd/lacuna.toml)")
    p.add_argument("--check", action="store_true", help="validate the config and load the models, then exit")
    p.set_defaults(func=_serve)

    p = cli.command("status", help="ask a running daemon for latency, counters, streams and models")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--connect", metavar="ENDPOINT", help=f"the daemon's ROUTER endpoint (default {DEFAULT_ENDPOINT})")
    g.add_argument("--config", metavar="FILE", help="read the ROUTER endpoint from this config")
    p.add_argument("--json", action="store_true", help="print the raw status map as JSON")
    p.add_argument("--timeout", type=float, default=5.0, metavar="S", help="seconds to wait for the answer (5)")
    p.add_argument("--key", metavar="FILE", help="CURVE: this client's NAME.key_secret (daemon with [security] keys)")
    p.add_argument("--server-key", metavar="FILE", help="CURVE: the daemon's public server.key")
    p.set_defaults(func=_status)


def _serve(args: argparse.Namespace) -> int:
    from daemon import config, models, server

    if args.check:
        cfg = config.load(args.config)
        table, errors = models.load_all(cfg)
        for n, e in errors.items():
            print(f"model {n}: {e}", file=sys.stderr)
        for n, m in table.items():
            print(f"model {n}: ok ({m.info()})")
        return 2 if errors else 0
    return server.serve(args.config)


def _status(args: argparse.Namespace) -> int:
    from clients.control import control
    from daemon import config

    ep = args.connect
    if args.config:
        cfg = config.load(args.config)
        if not cfg.zmq_router:
            raise ValueError(f"{args.config}: zmq.router is not set, so the daemon takes no control requests")
        ep = cfg.zmq_router
        if ep.endswith((":*", ":0")):
            raise ValueError(f"{args.config}: zmq.router {ep} is a wildcard port; the daemon logs the port it bound "
                             f"in its ready line: pass it with --connect")
    if bool(args.key) != bool(args.server_key):
        raise ValueError("--key and --server-key go together (CURVE needs both)")
    curve = (args.key, args.server_key) if args.key else None
    rep = control(ep or DEFAULT_ENDPOINT, "status", timeout_s=args.timeout, curve=curve)
    if args.json:
        print(json.dumps(rep.result, indent=2, default=str))
    else:
        print(render(rep.result))
    return 0


def _f(v: Any) -> str:
    return "-" if v is None else (f"{v:.3f}" if isinstance(v, float) else str(v))


def render(st: dict[str, Any]) -> str:
    """The status map as the table `lacuna status` prints."""
    L = [(f"lacuna daemon pid {st.get('pid')}, up {_f(st.get('uptime_s'))} s, config {st.get('config')}, "
          f"budget {_f(st.get('budget_ms'))} ms")]
    lat = st.get("latency", {})
    L.append("processing latency (ms): " + "  ".join(f"{k[:-3]} {_f(lat.get(k))}" for k in
                                                      ("p50_ms", "p90_ms", "p99_ms", "p999_ms", "max_ms"))
             + f"  (over {lat.get('window', 0)} of {lat.get('count', 0)} frames)")
    c = st.get("counters", {})
    L.append("frames: in {} out {} degraded {} dropped conflated/late/duplicate {}/{}/{} rejected {}".format(
        c.get("frames_in", 0), c.get("frames_out", 0), c.get("degraded", 0), c.get("dropped_conflated", 0),
        c.get("dropped_late", 0), c.get("dropped_duplicate", 0), c.get("rejected", 0)))
    other = {k: c[k] for k in ("bundles_in", "osc_bundles_in", "send_dropped", "send_errors", "internal_errors", "reloads",
                                "reload_failures", "expired", "osc_recv_errors") if c.get(k)}
    if other:
        L.append("other: " + ", ".join(f"{k} {v}" for k, v in other.items()))
    q = st.get("cpu_latency") or {}
    if q.get("requested_us") is not None:
        L.append(f"cpu latency request: {q['requested_us']} us, "
                 + (f"held (machine-wide bound now {_f(q.get('effective_us'))} us)" if q.get("held")
                    else f"NOT HELD: {q.get('error')}"))
    if st.get("rejected"):
        L.append("rejected by reason: " + ", ".join(f"{k} {v}" for k, v in sorted(st["rejected"].items())))
    L.append("models:")
    for n, m in sorted(st.get("models", {}).items()):
        star = "*" if n == st.get("default_model") else " "
        L.append(f" {star}{n:<14} {m.get('method', '?'):<12} channels {_f(m.get('channels')):<5} "
                 f"{m.get('file') or 'builtin ' + str(m.get('builtin'))}  (loaded {m.get('loaded_at')})")
    rl = st.get("reload") or {}
    if rl:
        L.append(f"last reload: {'ok' if rl.get('ok') else 'REFUSED: ' + '; '.join(f'{k}: {v}' for k, v in rl.get('errors', {}).items())}")
    streams = st.get("streams", {})
    total = st.get("streams_total", len(streams))
    L.append(f"streams: {total} open, {st.get('expired', 0)} expired"
             + (f" (the {len(streams)} most recently active below)" if total > len(streams) else ""))
    if streams:
        L.append(f"  {'stream':<20} {'model':<12} {'in':>8} {'out':>8} {'dropped':>8} {'rejected':>8} {'degraded':>8} "
                 f"{'predicted':>9} {'last seq':>9}")
        for sid, s in sorted(streams.items()):
            L.append(f"  {sid[:20]:<20} {s['model'][:12]:<12} {s['frames_in']:>8} {s['frames_out']:>8} {s['dropped']:>8} "
                     f"{s['rejected']:>8} {s['degraded']:>8} {s['predicted']:>9} {_f(s['last_seq']):>9}")
    if st.get("step_errors"):
        L.append(f"model step errors: {st['step_errors']} (last: {st.get('last_step_error')})")
    return "\n".join(L)
