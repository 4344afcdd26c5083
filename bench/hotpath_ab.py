"""CPU per frame of the daemon's per-frame path (bench/daemon_hotpath.py, no sockets), A/B across
checkouts in one run: the same driver runs each tree's daemon (PYTHONPATH=DIR), the trees
alternate and their order rotates from repeat to repeat.  Process CPU time, so a loaded machine
disturbs it less than round trips; the minimum over repeats is the figure least raised by the
other jobs, the median is given beside it.

    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python bench/hotpath_ab.py --root new=. \\
        --root main=/tmp/perf-main --root old=/tmp/perf-64e7005 --repeats 5 \\
        --json bench/results/hotpath_ab.json

Each tree's HLM is the one bench/echo_vs_daemon.py trained with that tree's code (its cache).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench.echo_vs_daemon import tree_hlm, tree_roots  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--root", action="append", default=[], metavar="NAME=DIR")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--behind", type=int, default=1, metavar="K",
                    help="also 64 bundled with K bundles read each turn (daemon_hotpath.py --behind)")
    ap.add_argument("--gap-ms", type=float, default=0.0,
                    help="sleep between ticks, as the live daemon waits for the next capture frame "
                         "(daemon_hotpath.py --gap-ms; then each tree's wall time of a tick's own work is the "
                         "figure to read, CPU time being charged by the scheduler tick)")
    ap.add_argument("--cache", default=os.path.join(tempfile.gettempdir(), "lacuna-echo-vs-daemon"))
    ap.add_argument("--json", dest="json_out", default=str(ROOT / "bench/results/hotpath_ab.json"))
    args = ap.parse_args(argv)
    roots = tree_roots(args.root)
    hlms = {n: tree_hlm(r, Path(args.cache)) for n, r in roots.items()}
    rows = []
    names = list(roots)
    for rep in range(args.repeats):
        for name in names[rep % len(names):] + names[:rep % len(names)]:
            out = Path(tempfile.mkdtemp(prefix="hotab-")) / "out.json"
            env = dict(os.environ, PYTHONPATH=str(roots[name]), OPENBLAS_NUM_THREADS="1")
            subprocess.run([sys.executable, str(ROOT / "bench/daemon_hotpath.py"), "--repeats", "1", "--frames",
                            str(args.frames), "--models", "floor", "--bundle", "--model", f"hlm={hlms[name]}",
                            "--behind", str(args.behind), "--gap-ms", str(args.gap_ms), "--json", str(out)], env=env, check=True, cwd=roots[name], stderr=subprocess.DEVNULL)
            for r in json.loads(out.read_text())["rows"]:
                rows.append({"repeat": rep, "tree": name, **r})
                r.setdefault("behind", 1)
                print(f"repeat {rep} {name:>5} {r['model']:>5} {r['streams']:>3}{' bundled' if r['bundle'] else '':8}"
                      f"{' x' + str(r['behind']) if r['behind'] > 1 else ''}: "
                      f"{r['cpu_us_per_frame_median']:.1f} us CPU/frame, wall {r.get('wall_us_per_frame_median', float('nan')):.1f}",
                      file=sys.stderr, flush=True)
    summary: dict[str, dict[str, float]] = {}
    for key in sorted({(r["model"], r["streams"], r["bundle"], r["behind"]) for r in rows}):
        case = f"{key[0]} {key[1]}{' bundled' if key[2] else ''}{f' {key[3]} a turn' if key[3] > 1 else ''}"
        s: dict[str, float] = {}
        for name in names:
            sel = [r for r in rows if r["tree"] == name and (r["model"], r["streams"], r["bundle"], r["behind"]) == key]
            v = [r["cpu_us_per_frame_median"] for r in sel]
            s[f"{name}_min"], s[f"{name}_median"] = float(np.min(v)), float(np.median(v))
            w = [r["wall_us_per_frame_median"] for r in sel if "wall_us_per_frame_median" in r]
            if w:
                s[f"{name}_wall_median"] = float(np.median(w))
        for name in names[1:]:
            s[f"{names[0]}_over_{name}_min"] = s[f"{names[0]}_min"] / s[f"{name}_min"]
            s[f"{names[0]}_over_{name}_median"] = s[f"{names[0]}_median"] / s[f"{name}_median"]
            if f"{name}_wall_median" in s and f"{names[0]}_wall_median" in s:
                s[f"{names[0]}_over_{name}_wall_median"] = s[f"{names[0]}_wall_median"] / s[f"{name}_wall_median"]
        summary[case] = s
    out = {"command": "python bench/hotpath_ab.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "roots": {k: str(v) for k, v in roots.items()}, "at": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "loadavg": os.getloadavg(), "gap_ms": args.gap_ms, "frames": "pan2009 test case 0 (bench/daemon_hotpath.py), left arm and head NaN",
           "summary": summary, "runs": rows}
    print(json.dumps(summary, indent=1))
    Path(args.json_out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
