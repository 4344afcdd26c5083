"""Wall time a frame of the daemon's bundled HLM tick and of its parts, ticks back to back or
``--gap-ms`` apart (a live tick starts cold: the daemon sleeps ~8 ms between ticks, and the caches
are the other processes' by then), A/B across checkouts in one run, alternating (issue 19,
bench/notebook/hlm64-7.md).

The driver is the daemon object's own tick as bench/daemon_hotpath.py drives it (64 streams of
CMU 35_08 with the left arm missing, one ``frames`` bundle a tick, its messages built
beforehand, the collector frozen after warm-up); the parts are timed by wrapping
``stepblock.run_block``, ``Scheduler.plan``, the HLM's ``step_block``, ``hlm.fast.step_rows_arrays``
and its compiled call, where the tree has them (each wrapper adds its own cold cost: compare
trees, not absolute figures).  Median over the ticks of each part, us a frame.

    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python bench/hlm_cold_tick.py --root new=. \\
        --root main=/tmp/main --model /tmp/lacuna-echo-vs-daemon/hlm-8bfa196.npz --gap-ms 8 --rounds 3
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PARTS = ("tick", "serve", "run_block", "plan", "step_block", "step_rows_arrays", "compiled")
N = 64


def frames_of(model: str):
    """(the model's channels, CMU 35_08 in their order with the left arm missing, float32)."""
    import numpy as np

    from lacuna.modelfile import load_model
    from mocap.datasets import load_trial

    ch = list(load_model(model).channels)
    take = load_trial("35_08")
    frames = take.frames[:, take.index(ch)].astype(np.float32)
    frames[:, [c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "lhand") for c in ch]] = np.nan
    return ch, frames


def child(model: str, gap_s: float, ticks: int, spread: bool = False, busy: bool = False,
          parts: tuple[str, ...] = PARTS) -> dict[str, float]:
    """us a frame of each of ``parts`` (those wrapped: the others of PARTS are not), median tick;
    ``spread``: stream i plays from its own offset i T / N (bench/hlm_cold_spread.py), else every
    stream the same frame; ``busy``: the gap spent spinning (the core stays this process's)."""
    import gc

    import numpy as np

    import hlm.fast as fast
    import hlm.model as hm
    from daemon import config, scheduler, stepblock, wire
    from daemon.models import load_all
    from daemon.server import Daemon
    from mocap import feature_model

    ch, frames = frames_of(model)
    T = len(frames)
    offsets = (np.arange(N) * (T // N)) % T if spread else np.zeros(N, int)
    cfg = config.from_dict({"daemon": {"budget_ms": 1000.0, "max_streams": 100000, "log_level": "warning"},
                            "models": {"hlm": {"file": model}}, "zmq": {"router": "tcp://127.0.0.1:*"}})
    d = Daemon(cfg)
    table, _ = load_all(cfg)
    d._install(table)
    held: list = []
    d._send = lambda o, m, publish=False: held.append(wire.to_map(m)) if len(o) == 3 else None
    d._send_fills = lambda o, maps: held.extend(maps)
    sids = [f"hlm-{i}" for i in range(N)]
    for sid in sids:
        d._handle(wire.encode(wire.Hello(sid, ch, "hlm")), ("router", [b"x"]), time.perf_counter())
    msgs = [wire.encode(wire.Bundle([wire.Frame(sid, k, k / 120, frames[(offsets[i] + k) % T])
                                     for i, sid in enumerate(sids)])) for k in range(ticks + 50)]
    acc: dict[str, float] = {}
    pc = time.perf_counter

    def wrap(obj, name: str, label: str) -> None:
        if label not in parts:
            return
        f = getattr(obj, name)

        def w(*a, **kw):
            t0 = pc()
            r = f(*a, **kw)
            acc[label] = acc.get(label, 0.0) + pc() - t0
            return r
        setattr(obj, name, w)

    wrap(stepblock, "run_block", "run_block")
    wrap(scheduler.Scheduler, "plan", "plan")
    wrap(hm.HLMModel if "step_block" in hm.HLMModel.__dict__ else feature_model.FeatureModel, "step_block", "step_block")
    wrap(fast, "step_rows_arrays", "step_rows_arrays")
    wrap(fast, "_block_rows" if hasattr(fast, "_block_rows") else "_step_rows", "compiled")
    wrap(d, "_serve", "serve")

    def tick(k: int) -> None:
        d._handle(msgs[k], ("router", [b"x"]), pc())
        d._serve()
        if held:
            wire.replies_of(held)
            held.clear()

    for k in range(50):
        tick(k)
    gc.collect()
    gc.freeze()
    per = []
    for k in range(50, 50 + ticks):
        acc.clear()
        t0 = pc()
        tick(k)
        acc["tick"] = pc() - t0
        per.append(dict(acc))
        if gap_s and busy:
            t1 = pc() + gap_s
            while pc() < t1:
                pass
        elif gap_s:
            time.sleep(gap_s)
    return {p: float(np.median([q.get(p, 0.0) for q in per])) / N * 1e6 for p in parts}


def main(argv: list[str] | None = None, spread: bool = False, prog: str = "bench/hlm_cold_tick.py",
         description: str = __doc__) -> int:
    """The A/B driver; ``spread``: bench/hlm_cold_spread.py's runs (its streams at their own phases,
    the parts without ``plan``, ``--env`` per tree, HLM_COLD_BUSY / HLM_COLD_GAP_MS in a child's)."""
    ap = argparse.ArgumentParser(prog=prog, description=description.split("\n\n")[0])
    ap.add_argument("--root", action="append", default=[], metavar="NAME=DIR")
    ap.add_argument("--model", required=True, help="an HLM file (the same for every tree)")
    ap.add_argument("--gap-ms", type=float, default=8.0)
    ap.add_argument("--ticks", type=int, default=300)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json", dest="json_out")
    ap.add_argument("--env", action="append", default=[], metavar="NAME:KEY=VALUE",
                    help="an environment variable for tree NAME's runs only (repeatable; two names may share a tree)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--spread", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    spread = spread or args.spread
    parts = tuple(p for p in PARTS if p != "plan") if spread else PARTS
    if args.child:
        gap = float(os.environ.get("HLM_COLD_GAP_MS", args.gap_ms))  # (a tree's own gap: --env NAME:HLM_COLD_GAP_MS=2)
        print(json.dumps(child(args.model, gap / 1000, args.ticks, spread, os.environ.get("HLM_COLD_BUSY") == "1", parts)))
        return 0
    sys.path.insert(0, str(ROOT))   # (here, not at the top: a child runs in another tree and imports nothing of this one's)
    from bench.echo_vs_daemon import rotated, tree_env, tree_roots

    roots = tree_roots(args.root)
    names = list(roots)
    rows = []
    for rnd in range(args.rounds):
        for name in rotated(names, rnd):
            env = tree_env(roots[name])
            env.update(kv.split(":", 1)[1].split("=", 1) for kv in args.env if kv.split(":", 1)[0] == name)
            out = subprocess.run([sys.executable, str(ROOT / "bench/hlm_cold_tick.py"), "--child", "--model", args.model,
                                  "--gap-ms", str(args.gap_ms), "--ticks", str(args.ticks)] + (["--spread"] if spread else []),
                                 env=env, cwd=roots[name], check=True, capture_output=True, text=True).stdout
            r = json.loads(out.strip().splitlines()[-1])
            rows.append({"round": rnd, "tree": name, "loadavg": os.getloadavg()[0], **r})
            print(f"round {rnd} {name:>5} (load {os.getloadavg()[0]:.2f}): " + ", ".join(f"{p} {r[p]:.2f}" for p in parts),
                  file=sys.stderr, flush=True)
    import numpy as np
    summary = {name: {p: float(np.median([r[p] for r in rows if r["tree"] == name])) for p in parts} for name in names}
    for name in names[1:]:
        summary[f"{names[0]}/{name}"] = {p: summary[names[0]][p] / summary[name][p] if summary[name][p] else float("nan")
                                         for p in parts}
    print(json.dumps(summary, indent=1))
    if args.json_out:
        Path(args.json_out).write_text(json.dumps({
            "command": f"python {prog} " + " ".join(argv if argv is not None else sys.argv[1:]),
            "at": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "gap_ms": args.gap_ms,
            "roots": {k: str(v) for k, v in roots.items()}, "summary": summary, "runs": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
