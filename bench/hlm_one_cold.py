"""Wall time of one HLM stream's step at the daemon's seam (``model.step_batch`` of one stream,
what ``Scheduler._step`` calls for a lone live stream), each frame ``--gap-ms`` after the last
(the daemon sleeps ~8 ms between a 120 Hz stream's frames, and what the CPU cached is the other
processes' by then), A/B across checkouts in one run, the trees' child processes alternating
(issue 19, bench/notebook/hlm9.md).

Frames: CMU 35_08 with the left arm missing (bench/echo_vs_daemon.py's one-stream case), each
made the way ``daemon.encode.model_inputs`` makes them (fresh (1, C) writable arrays) before the
clock starts; the first SKIP frames not counted.  The same model file for every tree.  Per round
and tree: p50 / p90 / p99 us a frame.

    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python bench/hlm_one_cold.py --root new=. \\
        --root main=/work/main --model /tmp/lacuna-echo-vs-daemon/hlm-83b719f.npz --gap-ms 8 --rounds 4
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SKIP = 50
MISSING = ("lhumerus", "lradius", "lwrist", "lhand")


def child(model: str, gap_s: float, frames_n: int) -> dict[str, float]:
    import numpy as np

    from lacuna.modelfile import load_model
    from mocap.datasets import load_trial

    m = load_model(model)
    tr = load_trial("35_08")
    ch = list(tr.channels)
    frames = tr.frames.astype(np.float64)[:, [ch.index(c) for c in m.channels]]
    obs = np.ones(frames.shape, bool)
    obs[:, [c.split(".")[0] in MISSING for c in m.channels]] = False
    st = m.stream()
    T = frames.shape[0]
    took = []
    gc.collect()
    gc.freeze()   # (as `lacuna serve` does after loading)
    for k in range(frames_n):
        o = obs[k % T][None].copy()
        f = np.where(o, frames[k % T][None], np.nan)
        t0 = time.perf_counter()
        m.step_batch([st], f, o)
        took.append(time.perf_counter() - t0)
        if gap_s:
            time.sleep(gap_s)
    p50, p90, p99 = np.percentile(np.array(took[SKIP:]) * 1e6, [50, 90, 99])
    return {"p50": float(p50), "p90": float(p90), "p99": float(p99)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", action="append", default=[], metavar="NAME=DIR")
    ap.add_argument("--model", required=True, help="an HLM file (the same for every tree)")
    ap.add_argument("--gap-ms", type=float, default=8.0)
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--json", dest="json_out")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.model, args.gap_ms / 1000, args.frames)))
        return 0
    sys.path.insert(0, str(ROOT))   # (here: a child runs in another tree and imports nothing of this one's)
    import numpy as np

    from bench.echo_vs_daemon import rotated, tree_env, tree_roots

    roots = tree_roots(args.root)
    names = list(roots)
    rows = []
    for rnd in range(args.rounds):
        for name in rotated(names, rnd):
            out = subprocess.run([sys.executable, str(ROOT / "bench/hlm_one_cold.py"), "--child", "--model", args.model,
                                  "--gap-ms", str(args.gap_ms), "--frames", str(args.frames)], env=tree_env(roots[name]),
                                 cwd=roots[name], check=True, capture_output=True, text=True).stdout
            r = json.loads(out.strip().splitlines()[-1])
            rows.append({"round": rnd, "tree": name, "loadavg": os.getloadavg()[0], **r})
            print(f"round {rnd} {name:>5} (load {os.getloadavg()[0]:.2f}): p50 {r['p50']:.1f} p90 {r['p90']:.1f} "
                  f"p99 {r['p99']:.1f} us", file=sys.stderr, flush=True)
    keys = ("p50", "p90", "p99")
    summary: dict[str, dict[str, float]] = {
        name: {p: float(np.median([r[p] for r in rows if r["tree"] == name])) for p in keys} for name in names}
    for name in names[1:]:
        # the ratio per round (the trees ran next to each other), then its median
        summary[f"{names[0]}/{name}"] = {p: float(np.median([
            a[p] / b[p] for a, b in zip([r for r in rows if r["tree"] == names[0]], [r for r in rows if r["tree"] == name])]))
            for p in keys}
    print(json.dumps(summary, indent=1))
    if args.json_out:
        Path(args.json_out).write_text(json.dumps({
            "command": "python bench/hlm_one_cold.py " + " ".join(argv if argv is not None else sys.argv[1:]),
            "at": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "gap_ms": args.gap_ms,
            "roots": {k: str(v) for k, v in roots.items()}, "summary": summary, "runs": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
