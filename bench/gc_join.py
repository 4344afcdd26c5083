"""Performers joining mid-session: the cyclic GC in the daemon's turns (issue 19, gc-10).

A live ``lacuna serve`` (pass-through, the load generator and frames of bench/echo_vs_daemon.py)
serves N bundled streams at 120 Hz on one connection; ``--join-at`` seconds in, M more
performers say hello on a second connection and send their own bundles.  The daemon process
records every cyclic GC run (``gc.callbacks``: start, duration, generation, objects collected,
objects in the collected generations at its start, and whether it ran inside a turn), every
turn's wall time, and the overdue drops per stream.  Reported per tree: the gen-2 runs (and
those inside a turn), the longest turn after the join, the already-running streams' overdue drops.
Trees alternate run by run (``--root NAME=DIR``).

    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python bench/gc_join.py --root new=. \\
        --root main=/work/main --repeats 3 --json bench/results/gc_join.json
"""
from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent

CHILD = r'''
import atexit, gc, json, os, sys, time, traceback
sys.path.insert(0, os.environ["PYTHONPATH"])
from daemon import loop, sessions as sessions_mod
pc = time.perf_counter
out = {"turns": [], "gc": [], "overdue": [], "hello": []}
T, G, O = out["turns"], out["gc"], out["overdue"]
st = {"t0": 0.0, "in_turn": False, "n": 0, "house": False}
def _gc(phase, info):
    g = info["generation"]
    if phase == "start":
        st["t0"] = pc()
        st["c0"] = time.thread_time()
        st["where"] = " < ".join(f"{os.path.basename(f.filename)}:{f.name}" for f in
                                 traceback.extract_stack(limit=6)[-6:-1][::-1]) if g == 2 else ""
        st["n"] = sum(gc.get_count()) if not os.environ.get("GCJ_COUNT") else \
            sum(len(gc.get_objects(i)) for i in range(g + 1))
    else:
        G.append((st["t0"], pc() - st["t0"], g, info["collected"], st["n"], st["in_turn"],
                  time.thread_time() - st["c0"], st["where"], st["house"]))
gc.callbacks.append(_gc)
_turn = loop.Daemon.turn
def turn(self, now, ready=None, items=None, arrived=None):
    t, c = pc(), time.thread_time()
    st["in_turn"] = True
    try:
        return _turn(self, now, ready, items, arrived)
    finally:
        st["in_turn"] = False
        T.append((t, pc() - t, len(self.sessions.sessions), time.thread_time() - c))
loop.Daemon.turn = turn
_hk = loop.Daemon._housekeeping
def housekeeping(self, now):
    st["house"] = True
    try:
        return _hk(self, now)
    finally:
        st["house"] = False
loop.Daemon._housekeeping = housekeeping
_ov = sessions_mod.SessionTable.overdue_seq
def overdue_seq(self, s, seq, origin):
    O.append((pc(), s.sid, seq))
    return _ov(self, s, seq, origin)
sessions_mod.SessionTable.overdue_seq = overdue_seq
def dump():
    with open(sys.argv[1], "w") as fh:
        json.dump(out, fh)
atexit.register(dump)
sys.exit(loop.serve(sys.argv[2]))
'''


def one_run(root: Path, args: argparse.Namespace, frames: Any, observed: Any, channels: list[str],
            tag: str) -> dict[str, Any]:
    from bench.echo_vs_daemon import tree_env
    from clients import loadgen
    from clients.client import control
    from clients.configfile import free_port, write_config
    from clients.session import DaemonUnavailable

    work = Path(tempfile.mkdtemp(prefix="gc-join-"))
    endpoint = f"tcp://127.0.0.1:{free_port()}"
    cfg = work / "lacuna.toml"
    write_config(cfg, {"daemon": {"default_model": "floor", "budget_ms": args.budget_ms, "max_streams": 4096,
                                  "log_level": "warning"}, "zmq": {"router": endpoint},
                       "models.floor": {"builtin": "passthrough", "channels": channels}})
    trace = work / "trace.json"
    log = open(work / "daemon.log", "ab")  # noqa: SIM115 - closed below
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(trace), str(cfg)], cwd=root, env=tree_env(root),
                            stdin=subprocess.DEVNULL, stdout=log, stderr=log)
    deadline = time.monotonic() + 120
    while True:
        try:
            control(endpoint, "status", timeout_s=0.5)
            break
        except DaemonUnavailable:
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError((work / "daemon.log").read_text()[-2000:]) from None
            time.sleep(0.1)
    res: dict[str, Any] = {}

    def load(key: str, n: int, seconds: float) -> None:
        res[key] = loadgen.run_load(endpoint, channels, frames, observed, n_streams=n, rate=args.rate,
                                    seconds=seconds, model="floor", prefix=f"{tag}{key}", progress=False,
                                    connections=1, bundle=True)

    first = threading.Thread(target=load, args=("a", args.streams, args.seconds))
    first.start()
    time.sleep(args.join_at)
    t_join = time.perf_counter()
    load("b", args.join, max(0.5, args.seconds - args.join_at - 1.0))
    first.join()
    proc.send_signal(signal.SIGTERM)
    proc.wait(30)
    log.close()
    tr = json.loads(trace.read_text())
    a, b = res["a"], res["b"]
    gcs, turns = tr["gc"], tr["turns"]
    # the join: the first turn that saw more sessions than the first group's
    join_t = next((t[0] for t in turns if t[2] > args.streams), t_join)
    after = [t for t in turns if join_t - 0.01 <= t[0] <= join_t + 1.0]
    # the turns that admitted the joining streams (their session count grew): wall and thread CPU
    adm = [t for p, t in zip(turns, turns[1:]) if t[2] > p[2] and t[2] > args.streams]
    ov_a = [o for o in tr["overdue"] if o[1].startswith(f"{tag}a")]
    return {"tree": tag, "a_sent": a.sent, "a_served": a.served, "a_dropped": a.dropped,
            "a_drop_reasons": a.drop_reasons, "b_sent": b.sent, "b_served": b.served, "b_dropped": b.dropped,
            "a_overdue_in_daemon": len(ov_a),
            "a_overdue_within_1s_of_join": sum(1 for o in ov_a if join_t - 0.01 <= o[0] <= join_t + 1.0),
            "join_turn_max_ms": round(max((t[1] for t in after), default=0.0) * 1e3, 3),
            "admitting_turns": len(adm),
            "admitting_cpu_ms_total": round(sum(t[3] for t in adm) * 1e3, 3),
            "admitting_cpu_ms_max": round(max((t[3] for t in adm), default=0.0) * 1e3, 3),
            "admitting_wall_ms_max": round(max((t[1] for t in adm), default=0.0) * 1e3, 3),
            "turn_ms_max": round(max((t[1] for t in turns), default=0.0) * 1e3, 3),
            "turns_over_4ms": sum(1 for t in turns if t[1] > 0.004),
            "gc_by_gen": {g: sum(1 for x in gcs if x[2] == g) for g in (0, 1, 2)},
            "gc_gen2_in_turn": sum(1 for x in gcs if x[2] == 2 and x[5] and not x[8]),
            "gc_gen2_in_housekeeping": sum(1 for x in gcs if x[2] == 2 and x[8]),
            "gc_in_turn_ms_max": round(max((x[1] for x in gcs if x[5]), default=0.0) * 1e3, 3),
            "gc_ms_max": round(max((x[1] for x in gcs), default=0.0) * 1e3, 3),
            "gc_long": [{"t_from_join_s": round(x[0] - join_t, 4), "ms": round(x[1] * 1e3, 3), "gen": x[2],
                         "collected": x[3], "objects_at_start": x[4], "in_turn": x[5], "in_housekeeping": x[8],
                         "cpu_ms": round(x[6] * 1e3, 3), "where": x[7]}
                        for x in gcs if x[1] > 0.001 or x[2] == 2]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--root", action="append", default=[], help="NAME=DIR, repeatable (default new=this checkout)")
    ap.add_argument("--streams", type=int, default=64)
    ap.add_argument("--join", type=int, default=64)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--join-at", type=float, default=2.0)
    ap.add_argument("--rate", type=float, default=120.0)
    ap.add_argument("--budget-ms", type=float, default=4.0)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--json", dest="json_out", default=str(ROOT / "bench/results/gc_join.json"))
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    import numpy as np

    from bench.echo_vs_daemon import MISSING, TEST, TRAIN, rotated, tree_roots
    from mocap.datasets import load_trial

    roots = tree_roots(args.root)
    test = load_trial(TEST)
    channels = list(load_trial(TRAIN[0]).channels)
    frames = test.frames[:, test.index(channels)].astype(np.float32)
    observed = np.broadcast_to(~np.array([c.split(".")[0] in MISSING for c in channels]), frames.shape).copy()
    runs: list[dict[str, Any]] = []
    for rep in range(args.repeats):
        for name in rotated(list(roots), rep):
            row = one_run(roots[name], args, frames, observed, channels, name)
            row["repeat"] = rep
            runs.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    Path(args.json_out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json_out).write_text(json.dumps({"command": " ".join(sys.argv), "roots": {k: str(v) for k, v in roots.items()},
                                               "at": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                                               "runs": runs}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
