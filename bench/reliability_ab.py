"""docs/RELIABILITY.md's figures, paired: two checkouts alternating, rounds x trees.

Each round runs, in each tree (the order rotating from round to round, so none always goes
first), under ``nice``:

* the overload soak, ``bench/reliability_soak.py --repeats 1`` (section 3: served/offered,
  drops, proc_us p50/p99, RSS);
* ``starved`` (not in the default jobs): that soak for 10 s with its daemon starved,
  ``--starved 0.2``, and the daemon's CPU per frame sent (served + dropped + lost);
* the fuzz test (section 1: 100,600 malformed messages, time until all are counted, msg/s,
  daemon RSS), ``pytest -s tests/test_reliability_fuzz.py``, its printed line parsed;
* the SIGKILL restart and slow-consumer fault tests (section 2: time until three streams are
  served again; stuck subscriber, RSS), ``pytest -s`` of those two, their lines parsed;
* the CPU cost of a rejected message (section 1), ``bench/reliability_reject_cost.py --repeats 3``.

The 1-minute load average is read before and after each job.  Each tree runs with its own
code (``PYTHONPATH`` = the tree, its working directory the tree) and the same interpreter.
Counts are exact; timings under a shared machine's load are read as ratios within a round.

    .venv/bin/python bench/reliability_ab.py --trees /tmp/old-ff143a6 . --rounds 3 --json bench/results/reliability_ab.json
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

FUZZ = re.compile(r"all counted after ([\d.]+) s \((\d+) msg/s\); daemon rejected (\d+).*?daemon RSS (\d+) KiB")
KILL = re.compile(r"served again after ([\d.]+) s")
SLOW = re.compile(r"(\d+) fills published, the stuck subscriber got (\d+).*?daemon RSS (\d+) -> (\d+) KiB; "
                  r"good stream p50 proc (\d+) us")


def run(tree: Path, cmd: list[str], timeout: float) -> tuple[int, str, float, float, float]:
    env = dict(os.environ, PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1")
    l0, t0 = os.getloadavg()[0], time.perf_counter()
    p = subprocess.run(["nice", "-n", "5", *cmd], cwd=tree, env=env, capture_output=True, text=True, timeout=timeout)
    return p.returncode, p.stdout + p.stderr, time.perf_counter() - t0, l0, os.getloadavg()[0]


def soak(tree: Path, py: str) -> dict:
    with tempfile.NamedTemporaryFile(suffix=".json") as fh:
        rc, out, wall, l0, l1 = run(tree, [py, "bench/reliability_soak.py", "--repeats", "1", "--json", fh.name], 600)
        got = json.loads(Path(fh.name).read_text() or "{}") if rc in (0, 1) else {}
    med = got.get("median", {})
    return {"rc": rc, "wall_s": wall, "load": [l0, l1], **{k: med.get(k) for k in (
        "offered_per_s", "served_per_s", "dropped", "degraded", "lost", "proc_p50_ms", "proc_p99_ms",
        "proc_within_budget", "rss_start_kib", "rss_quarter_kib", "rss_end_kib", "rss_max_kib")},
        "tail": "" if med else out[-800:]}


def starved(tree: Path, py: str) -> dict:
    """The soak with its daemon starved (``--starved 0.2``, 10 s): its CPU per frame sent, where
    nearly every frame is answered ``overdue`` or ``conflated`` (bench/notebook/replay-4.md)."""
    with tempfile.NamedTemporaryFile(suffix=".json") as fh:
        rc, out, wall, l0, l1 = run(tree, [py, "bench/reliability_soak.py", "--repeats", "1", "--seconds", "10",
                                           "--starved", "0.2", "--json", fh.name], 600)
        got = json.loads(Path(fh.name).read_text() or "{}") if rc in (0, 1) else {}
    med = got.get("median", {})
    frames = sum(med.get(k) or 0 for k in ("served", "dropped", "lost"))
    return {"rc": rc, "wall_s": wall, "load": [l0, l1], **{k: med.get(k) for k in (
        "served", "dropped", "lost", "daemon_cpu_s", "rss_max_kib")},
        "cpu_us_per_frame": 1e6 * med["daemon_cpu_s"] / frames if frames else None, "tail": "" if med else out[-800:]}


def fuzz(tree: Path, py: str) -> dict:
    rc, out, wall, l0, l1 = run(tree, [py, "-m", "pytest", "-q", "-s", "-p", "no:cacheprovider",
                                       "tests/test_reliability_fuzz.py"], 900)
    m = FUZZ.search(out)
    return {"rc": rc, "wall_s": wall, "load": [l0, l1],
            **({"counted_after_s": float(m[1]), "msg_per_s": int(m[2]), "rejected": int(m[3]), "rss_kib": int(m[4])}
               if m else {"tail": out[-800:]})}


def faults(tree: Path, py: str) -> dict:
    rc, out, wall, l0, l1 = run(tree, [py, "-m", "pytest", "-q", "-s", "-p", "no:cacheprovider",
                                       "tests/test_reliability_faults.py", "-k", "sigkilled or slow_consumers"], 900)
    k, s = KILL.search(out), SLOW.search(out)
    d: dict = {"rc": rc, "wall_s": wall, "load": [l0, l1]}
    if k:
        d["resumed_s"] = float(k[1])
    if s:
        d.update(published=int(s[1]), stuck_got=int(s[2]), rss0_kib=int(s[3]), rss1_kib=int(s[4]), good_p50_us=int(s[5]))
    if not (k and s):
        d["tail"] = out[-800:]
    return d


def reject(tree: Path, py: str) -> dict:
    with tempfile.NamedTemporaryFile(suffix=".json") as fh:
        rc, out, wall, l0, l1 = run(tree, [py, "bench/reliability_reject_cost.py", "--repeats", "3", "--json", fh.name], 600)
        got = json.loads(Path(fh.name).read_text() or "{}") if rc == 0 else {}
    med = got.get("us_cpu_per_rejected_message_median", {})
    return {"rc": rc, "wall_s": wall, "load": [l0, l1], "limited_us": med.get("limited"),
            "every_line_us": med.get("every_line"), **({} if med else {"tail": out[-800:]})}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trees", nargs="+", required=True, help="checkouts, before first")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--jobs", default="soak,fuzz,faults,reject")
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args(argv)
    trees = [Path(t).resolve() for t in args.trees]
    py = sys.executable
    jobs = {"soak": soak, "starved": starved, "fuzz": fuzz, "faults": faults, "reject": reject}
    rounds = []
    for r in range(args.rounds):
        order = trees[r % len(trees):] + trees[:r % len(trees)]  # each tree first in turn
        row: dict = {}
        for name in args.jobs.split(","):
            for t in order:
                res = jobs[name](t, py)
                row.setdefault(name, {})[str(t)] = res
                print(f"round {r + 1} {name} {t.name}: " + json.dumps({k: v for k, v in res.items() if k != "tail"}),
                      file=sys.stderr, flush=True)
                if "tail" in res:
                    print(res["tail"], file=sys.stderr)
        rounds.append(row)
        if args.json_out:
            Path(args.json_out).write_text(json.dumps({"trees": [str(t) for t in trees], "rounds": rounds}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
