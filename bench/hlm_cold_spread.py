"""bench/hlm_cold_tick.py with the 64 streams at different phases, as live: stream i plays CMU
35_08 (left arm missing) from its own offset i T / 64, as clients.loadgen does, where
hlm_cold_tick gives every stream the same frame (one posterior support shared by all streams, so
the filter's tables a tick reads are one stream's).  Same driver (the daemon object's bundled
tick, messages built beforehand, collector frozen), same parts, A/B across trees in one run,
rounds alternating; also the support size k of the posterior per frame (``--support``: one tree,
in process, from the compiled step's own k), bench/notebook/hlm64-12.md.  ``HLM_COLD_BUSY=1`` in a
tree's environment (``--env NAME:HLM_COLD_BUSY=1``) spends the gap spinning instead of sleeping;
``HLM_COLD_GAP_MS`` gives a tree its own gap (a gap sweep in one run, names sharing a tree).

    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python bench/hlm_cold_spread.py --root new=. \\
        --root main=/work/wt-hlm12-main --model /tmp/lacuna-echo-vs-daemon/hlm-e9b3d79.npz --gap-ms 8 --rounds 4
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
PARTS = ("tick", "serve", "run_block", "step_block", "step_rows_arrays", "compiled")
N = 64


def _frames(model: str):
    import numpy as np

    from lacuna.modelfile import load_model
    from mocap.datasets import load_trial

    ch = list(load_model(model).channels)
    take = load_trial("35_08")
    frames = take.frames[:, take.index(ch)].astype(np.float32)
    frames[:, [c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "lhand") for c in ch]] = np.nan
    return ch, frames


def child(model: str, gap_s: float, ticks: int) -> dict[str, float]:
    import gc

    import numpy as np

    import hlm.fast as fast
    import hlm.model as hm
    from daemon import config, stepblock, wire
    from daemon.models import load_all
    from daemon.server import Daemon

    ch, frames = _frames(model)
    T = len(frames)
    offsets = (np.arange(N) * (T // N)) % T
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
        f = getattr(obj, name)

        def w(*a, **kw):
            t0 = pc()
            r = f(*a, **kw)
            acc[label] = acc.get(label, 0.0) + pc() - t0
            return r
        setattr(obj, name, w)

    wrap(stepblock, "run_block", "run_block")
    wrap(hm.HLMModel, "step_block", "step_block")
    wrap(fast, "step_rows_arrays", "step_rows_arrays")
    wrap(fast, "_block_rows", "compiled")
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
        if gap_s and os.environ.get("HLM_COLD_BUSY") == "1":  # (the gap spent spinning: the core stays this process's)
            t1 = pc() + gap_s
            while pc() < t1:
                pass
        elif gap_s:
            time.sleep(gap_s)
    return {p: float(np.median([q.get(p, 0.0) for q in per])) / N * 1e6 for p in PARTS}


def support(model: str, frames_n: int) -> dict:
    """The posterior's support per stream-frame (states with non-zero mass after the update: the
    k the compiled step visits) and how many states hold at least a fraction eps of the largest
    mass, over 64 streams at spread offsets stepped by ``step_block``, in process (one tree)."""
    import numpy as np

    from lacuna.modelfile import load_model

    m = load_model(model)
    ch, frames = _frames(model)
    T = len(frames)
    offsets = (np.arange(N) * (T // N)) % T
    obs = np.isfinite(frames)
    streams = [m.stream() for _ in range(N)]
    rows = np.array([s.slot for s in streams])
    eps = (0.0, 1e-200, 1e-100, 1e-60, 1e-30, 1e-16, 1e-12, 1e-10, 1e-8, 1e-6, 1e-4)
    got: dict[float, list[int]] = {e: [] for e in eps}
    for k in range(frames_n):
        idx = (offsets + k) % T
        f = np.where(obs[idx], frames[idx], 0.0).astype(np.float64)
        m.step_block(streams, f, obs[idx].copy(), None)
        if k < 20:
            continue
        P = m.pool.core["post"][rows].reshape(N, -1)
        top = P.max(1, keepdims=True)
        for e in eps:
            got[e].extend((P > e * top).sum(1).tolist() if e else (P != 0).sum(1).tolist())
    return {str(e): {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)), "max": int(max(v)),
                     "mean": float(np.mean(v))} for e, v in got.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", action="append", default=[], metavar="NAME=DIR")
    ap.add_argument("--model", required=True, help="an HLM file (the same for every tree)")
    ap.add_argument("--gap-ms", type=float, default=8.0)
    ap.add_argument("--ticks", type=int, default=300)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json", dest="json_out")
    ap.add_argument("--env", action="append", default=[], metavar="NAME:KEY=VALUE",
                    help="an environment variable for tree NAME's runs only (repeatable; two names may share a tree)")
    ap.add_argument("--support", type=int, default=0, metavar="FRAMES",
                    help="only count the posterior's support over this many frames (this tree, in process)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.support:
        sys.path.insert(0, str(ROOT))
        print(json.dumps(support(args.model, args.support), indent=1))
        return 0
    if args.child:
        gap = float(os.environ.get("HLM_COLD_GAP_MS", args.gap_ms))  # (a tree's own gap: --env NAME:HLM_COLD_GAP_MS=2)
        print(json.dumps(child(args.model, gap / 1000, args.ticks)))
        return 0
    sys.path.insert(0, str(ROOT))   # (a child runs in another tree and imports nothing of this one's)
    from bench.echo_vs_daemon import rotated, tree_env, tree_roots

    roots = tree_roots(args.root)
    names = list(roots)
    rows = []
    for rnd in range(args.rounds):
        for name in rotated(names, rnd):
            env = tree_env(roots[name])
            env.update(kv.split(":", 1)[1].split("=", 1) for kv in args.env if kv.split(":", 1)[0] == name)
            out = subprocess.run([sys.executable, str(ROOT / "bench/hlm_cold_spread.py"), "--child", "--model",
                                  args.model, "--gap-ms", str(args.gap_ms), "--ticks", str(args.ticks)], env=env,
                                 cwd=roots[name], check=True, capture_output=True, text=True).stdout
            r = json.loads(out.strip().splitlines()[-1])
            rows.append({"round": rnd, "tree": name, "loadavg": os.getloadavg()[0], **r})
            print(f"round {rnd} {name:>5} (load {os.getloadavg()[0]:.2f}): " + ", ".join(f"{p} {r[p]:.2f}" for p in PARTS),
                  file=sys.stderr, flush=True)
    import numpy as np
    summary = {name: {p: float(np.median([r[p] for r in rows if r["tree"] == name])) for p in PARTS} for name in names}
    for name in names[1:]:
        summary[f"{names[0]}/{name}"] = {p: summary[names[0]][p] / summary[name][p] if summary[name][p] else float("nan")
                                         for p in PARTS}
    print(json.dumps(summary, indent=1))
    if args.json_out:
        Path(args.json_out).write_text(json.dumps({
            "command": "python bench/hlm_cold_spread.py " + " ".join(argv if argv is not None else sys.argv[1:]),
            "at": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "gap_ms": args.gap_ms,
            "roots": {k: str(v) for k, v in roots.items()}, "summary": summary, "runs": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
