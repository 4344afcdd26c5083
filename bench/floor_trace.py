"""A live ``lacuna serve`` pass-through at 64 bundled streams, traced turn by turn (issue 19, floor-7).

Why a frame is dropped ``overdue`` while a bare echo keeps up: the daemon decides from its own
clock (daemon/tickblock.py: a bundle read at ``arrived`` is dropped before the step when
``arrived + budget < t0 + n * send_cost``, after it when its replies would leave over budget),
so this records, in the real daemon process with real sockets and the load generator of
bench/echo_vs_daemon.py, for every turn: when the loop woke and how late (daemon/stalls.py's
``due``), how many messages it read, each bundle's receipt time, when its tick began, the
scheduler's send/encode estimates, the bundle's drops (before / after the step), the time spent
sending, and every cyclic GC run (``gc.callbacks``) with its generation and duration.  The
wrappers cost a few microseconds a turn; the trace is for finding the late turns, not for CPU
figures (bench/echo_vs_daemon.py gives those).

    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python bench/floor_trace.py --seconds 8 \\
        --json bench/results/floor_trace.json [--root DIR] [--repeats 3]

``--py-spy FILE`` also records the daemon with py-spy (``--native``, speedscope format) while
the load runs; ``--perf FILE`` with ``perf record -g``.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent

CHILD = r'''
import atexit, gc, json, os, sys, time, traceback
sys.path.insert(0, os.environ["PYTHONPATH"])
from daemon import loop, stalls, tickblock, sessions as sessions_mod, outbox
out = {"turns": [], "blocks": [], "gc": [], "overdue": []}
T, B, G, O = out["turns"], out["blocks"], out["gc"], out["overdue"]
pc = time.perf_counter
tt = time.thread_time
_ss = open("/proc/thread-self/schedstat", "rb", buffering=0)
def rq():
    """ns this thread has waited on a run queue (runnable, another task on its CPU)."""
    _ss.seek(0)
    f = _ss.read().split()
    return int(f[1]) / 1e9 + int(f[2]) * 1e3  # (+ 1000 s per time it was switched in: split in analyse)
_gc0 = [0.0, ""]
def _gc(phase, info):
    if phase == "start":
        _gc0[0] = pc()
        _gc0[1] = " < ".join(f"{os.path.basename(f.filename)}:{f.name}" for f in
                             traceback.extract_stack(limit=6)[-6:-1][::-1]) if info["generation"] == 2 else ""
    else:  # (the caller of a full collection: an explicit gc.collect, or the allocation that set it off)
        G.append((_gc0[0], pc() - _gc0[0], info["generation"], info["collected"], _gc0[1]))
gc.callbacks.append(_gc)
_woke = stalls.Stalls.woke
def woke(self, due):
    _woke(self, due)
    self._tr_due = due
stalls.Stalls.woke = woke
_turn = loop.Daemon.turn
def turn(self, now, ready=None, items=None, arrived=None):
    t, c, q, m = pc(), tt(), rq(), len(sys.modules)
    r = _turn(self, now, ready, items, arrived)
    T.append((getattr(self.stalls, "_tr_due", 0.0), self.stalls._woke_at or 0.0, t, pc(), bool(ready), arrived,
              tt() - c, rq() - q, len(sys.modules) - m))
    return r
loop.Daemon.turn = turn
_hk = loop.Daemon._housekeeping
def housekeeping(self, now):
    t, c = pc(), tt()
    _hk(self, now)
    B.append(("house", t, pc() - t, tt() - c))
loop.Daemon._housekeeping = housekeeping
_batch = loop.Daemon._batch
def batch(self, items):
    B.append(("read", pc(), len(items), [a for _, _, a in items], tt(), rq()))
    return _batch(self, items)
loop.Daemon._batch = batch
_sb = tickblock.BlockTick._serve_block
def serve_block(self, bw):
    t, c, q = pc(), tt(), rq()
    sc = self.sched
    est = (sc.send_cost, sc.encode_cost)
    c0 = (self.sessions.block_overdue, self.metrics.counters.get("overdue_after_step", 0))
    r = _sb(self, bw)
    c1 = (self.sessions.block_overdue, self.metrics.counters.get("overdue_after_step", 0))
    B.append(("block", t, pc(), bw.arrived, len(bw.plan.table), est, c1[0] - c0[0], c1[1] - c0[1], r, c, tt() - c, q, rq() - q))
    return r
tickblock.BlockTick._serve_block = serve_block
_ov = sessions_mod.SessionTable.overdue_seq
def overdue_seq(self, s, seq, origin):
    O.append((pc(), s.sid, seq))
    return _ov(self, s, seq, origin)
sessions_mod.SessionTable.overdue_seq = overdue_seq
_fm = outbox.Outbox.send_fill_maps
def send_fill_maps(self, origin, maps):
    t = pc()
    r = _fm(self, origin, maps)
    B.append(("fills", t, pc() - t, len(maps)))
    return r
outbox.Outbox.send_fill_maps = send_fill_maps
_sh = outbox.Outbox.send_held
def send_held(self, *a, **k):
    t = pc()
    r = _sh(self, *a, **k)
    if r:
        B.append(("send", t, pc() - t, r))
    return r
outbox.Outbox.send_held = send_held
def dump():
    with open(sys.argv[1], "w") as fh:
        json.dump(out, fh)
atexit.register(dump)
from daemon.loop import serve
sys.exit(serve(sys.argv[2]))
'''


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--root", default=str(ROOT), help="the code tree whose daemon runs")
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--rate", type=float, default=120.0)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--budget-ms", type=float, default=4.0)
    ap.add_argument("--py-spy", dest="pyspy", default=None)
    ap.add_argument("--perf", default=None)
    ap.add_argument("--no-trace", action="store_true", help="run the daemon untraced (lacuna serve as is)")
    ap.add_argument("--json", dest="json_out", default=str(ROOT / "bench/results/floor_trace.json"))
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    import numpy as np

    from bench.echo_vs_daemon import MISSING, TEST, TRAIN, tree_env
    from clients import loadgen
    from clients.client import control
    from clients.configfile import free_port, write_config
    from clients.harness import cpu_seconds
    from clients.session import DaemonUnavailable
    from mocap.datasets import load_trial

    root = Path(args.root).resolve()
    test = load_trial(TEST)
    channels = list(load_trial(TRAIN[0]).channels)
    frames = test.frames[:, test.index(channels)].astype(np.float32)
    observed = np.broadcast_to(~np.array([c.split(".")[0] in MISSING for c in channels]), frames.shape).copy()
    results: list[dict[str, Any]] = []
    for rep in range(args.repeats):
        work = Path(tempfile.mkdtemp(prefix="floor-trace-"))
        endpoint = f"tcp://127.0.0.1:{free_port()}"
        cfg = work / "lacuna.toml"
        write_config(cfg, {"daemon": {"default_model": "floor", "budget_ms": args.budget_ms, "max_streams": 4096,
                                      "log_level": "warning"}, "zmq": {"router": endpoint},
                           "models.floor": {"builtin": "passthrough", "channels": channels}})
        trace = work / "trace.json"
        cmd = [sys.executable, "-m", "lacuna.cli", "serve", "--config", str(cfg)] if args.no_trace else \
            [sys.executable, "-c", CHILD, str(trace), str(cfg)]
        log = open(work / "daemon.log", "ab")  # noqa: SIM115
        proc = subprocess.Popen(cmd, cwd=root, env=tree_env(root), stdin=subprocess.DEVNULL, stdout=log, stderr=log)
        deadline = time.monotonic() + 120
        while True:
            try:
                control(endpoint, "status", timeout_s=0.5)
                break
            except DaemonUnavailable:
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError((work / "daemon.log").read_text()[-2000:]) from None
                time.sleep(0.1)
        prof = None
        if args.pyspy:
            prof = subprocess.Popen([str(Path(sys.executable).parent / "py-spy"), "record", "--native", "-r", "500",
                                     "-f", "raw", "-o", f"{args.pyspy}.{rep}.txt", "-p", str(proc.pid),
                                     "-d", str(int(args.seconds) + 2)], stdout=subprocess.DEVNULL,
                                    stderr=subprocess.DEVNULL)
        elif args.perf:
            prof = subprocess.Popen(["perf", "record", "-F", "2000", "-g", "-o", f"{args.perf}.{rep}", "-p",
                                     str(proc.pid), "--", "sleep", str(args.seconds + 1)],
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(0.5 if prof else 0.0)
        load0 = os.getloadavg()
        st0 = _steal()
        c0 = cpu_seconds(proc.pid)
        th0 = _threads(proc.pid)
        res = loadgen.run_load(endpoint, channels, frames, observed, n_streams=64, rate=args.rate,
                               seconds=args.seconds, model="floor", prefix=f"tr{rep}", progress=False,
                               connections=1, bundle=True)
        c1 = cpu_seconds(proc.pid)
        th1 = _threads(proc.pid)
        st1 = _steal()
        st = control(endpoint, "status", timeout_s=5.0).result
        if prof is not None:
            prof.wait(60)
        proc.send_signal(signal.SIGTERM)
        proc.wait(30)
        log.close()
        row: dict[str, Any] = {
            "repeat": rep, "sent": res.sent, "served": res.served, "dropped": res.dropped,
            "drop_reasons": res.drop_reasons, **loadgen.percentiles(res.rtt_ms),
            "cpu_us_per_frame": 1e6 * (c1 - c0) / max(1, res.sent) if c0 is not None and c1 is not None else None,
            "loadavg": [load0, os.getloadavg()],
            "threads_us_per_frame": {k: round(1e6 * (v - th0.get(k, 0.0)) / max(1, res.sent), 2) for k, v in th1.items()},
            "machine_s": {k: round((st1[k] - st0[k]) / os.sysconf("SC_CLK_TCK"), 2) for k in st0},
            "daemon_loop": st.get("loop"), "counters": {k: v for k, v in st.get("counters", {}).items()
                                                         if "overdue" in k or k in ("ticks", "frames_out")}}
        if not args.no_trace:
            row["analysis"] = analyse(json.loads(trace.read_text()), args.budget_ms / 1e3)
        results.append(row)
        print(json.dumps(row, indent=1), file=sys.stderr, flush=True)
    Path(args.json_out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json_out).write_text(json.dumps({"command": " ".join(sys.argv), "root": str(root),
                                               "at": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                                               "runs": results}, indent=1))
    return 0


def analyse(tr: dict[str, Any], budget: float) -> dict[str, Any]:
    """Each bundle that lost frames overdue: what the turn around it was doing."""
    ev = tr["blocks"]
    blocks = [e for e in ev if e[0] == "block"]
    reads = [e for e in ev if e[0] == "read"]
    gcs = tr["gc"]
    turns = tr["turns"]
    late: list[dict[str, Any]] = []
    for b in blocks:
        _, t0, t1, arrived, n, est, early, after, _, c0, cpu, q0, qstep = b
        if not (early or after):
            continue
        turn = next((t for t in turns if t[2] <= t0 <= t[3]), None)
        near = [r for r in reads if arrived - 0.02 <= r[1] <= t1]
        rd = next((r for r in reads if arrived in r[3]), None)
        cpu_wait = None if rd is None else round((c0 - rd[4]) * 1e3, 3)
        rq_wait = None if rd is None else _rq(q0 - rd[5])
        late.append({"t": round(t0 - blocks[0][1], 4), "waited_ms": round((t0 - arrived) * 1e3, 3),
                     "cpu_read_to_tick_ms": cpu_wait, "runqueue_read_to_tick_ms": rq_wait,
                     "runqueue_step_ms": _rq(qstep),
                     "step_ms": round((t1 - t0) * 1e3, 3), "step_cpu_ms": round(cpu * 1e3, 3), "early": early, "after": after, "n": n,
                     "send_cost_us": round(est[0] * 1e6, 2), "encode_cost_us": round(est[1] * 1e6, 2),
                     "turn": None if turn is None else {"late_wake_ms": round((turn[1] - turn[0]) * 1e3, 3),
                                                        "woke_to_turn_ms": round((turn[2] - turn[1]) * 1e3, 3),
                                                        "turn_ms": round((turn[3] - turn[2]) * 1e3, 3),
                                                        "turn_cpu_ms": round(turn[6] * 1e3, 3),
                                                        "arrived_given": turn[5] is not None},
                     "reads": [(round((r[1] - arrived) * 1e3, 3), r[2], [round((a - arrived) * 1e3, 3) for a in r[3]])
                               for r in near],
                     "gc": [(round((g[0] - arrived) * 1e3, 3), round(g[1] * 1e3, 3), g[2]) for g in gcs
                            if arrived - 0.005 <= g[0] <= t1]})
    ok = [b for b in blocks if not (b[6] or b[7])]
    waits = sorted((b[1] - b[3]) * 1e3 for b in blocks)
    sends = sorted(e[2] * 1e6 for e in ev if e[0] == "fills")
    wakes = sorted((t[1] - t[0]) * 1e3 for t in turns if t[0])
    return {"blocks": len(blocks), "blocks_with_drops": len(late), "served_ok": len(ok),
            "wait_ms_p50_p99_max": _pcts(waits), "send_fill_maps_us_p50_p99_max": _pcts(sends),
            "late_wake_ms_p50_p99_max": _pcts(wakes),
            "housekeeping_wall_cpu_ms": [(round(e[2] * 1e3, 3), round(e[3] * 1e3, 3)) for e in ev if e[0] == "house"],
            "gc_runs": len(gcs), "gc_ms_max": round(max((g[1] for g in gcs), default=0.0) * 1e3, 3),
            "gc_by_gen": {g: sum(1 for x in gcs if x[2] == g) for g in (0, 1, 2)},
            "reads_with_2plus": sum(1 for r in reads if r[2] > 1),
            "gcs": [(round(g[1] * 1e3, 3), g[2], g[3], g[4] if len(g) > 4 else "") for g in gcs
                    if g[1] > 0.0005 or g[2] == 2],
            "long_turns_wall_cpu_runqueue_ms": [(round((t[3] - t[2]) * 1e3, 3), round(t[6] * 1e3, 3), _rq(t[7]))
                                                for t in turns if t[3] - t[2] > 0.003],
            "turns_importing": [(round((t[2] - turns[0][2]), 3), t[8], round((t[3] - t[2]) * 1e3, 3)) for t in turns if t[8]],
            "runqueue_ms_total_switches": _rq(sum(t[7] for t in turns)),
            "turn_wall_ms_total": round(sum(t[3] - t[2] for t in turns) * 1e3, 3),
            "turn_cpu_ms_total": round(sum(t[6] for t in turns) * 1e3, 3),
            "late_by_cause": _causes(late),
            "late": late[:40]}


def _causes(late: list[dict[str, Any]]) -> dict[str, int]:
    """Each dropped bundle's lost time (wall - thread CPU from read to the end of its step), by
    where it went: waiting on a run queue (another task had the core), neither running nor
    switched out (the vCPU itself stopped: hypervisor steal), or our own CPU (wall ~ CPU)."""
    out = {"runqueue": 0, "steal_or_blocked": 0, "own_cpu": 0, "unknown": 0}
    for x in late:
        if x["cpu_read_to_tick_ms"] is None:
            out["unknown"] += 1
            continue
        wall = x["waited_ms"] + x["step_ms"]
        cpu = x["cpu_read_to_tick_ms"] + x["step_cpu_ms"]
        rq = x["runqueue_read_to_tick_ms"][0] + x["runqueue_step_ms"][0]
        off = wall - cpu
        if off < 0.5 * wall:
            out["own_cpu"] += 1
        elif rq >= 0.5 * off:
            out["runqueue"] += 1
        else:
            out["steal_or_blocked"] += 1
    return out


def _threads(pid: int) -> dict[str, float]:
    """CPU seconds of each thread of ``pid`` (name/tid), from /proc."""
    out: dict[str, float] = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/stat") as fh:
                st = fh.read()
        except OSError:
            continue
        name = st[st.index("(") + 1:st.rindex(")")]
        f = st[st.rindex(")") + 2:].split()
        out[f"{name}/{tid}"] = (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")
    return out


def _steal() -> dict[str, int]:
    """The machine's CPU jiffies (both cores) from /proc/stat: busy, idle, steal."""
    with open("/proc/stat") as fh:
        f = [int(x) for x in fh.readline().split()[1:]]
    return {"user_nice_sys": f[0] + f[1] + f[2] + f[5] + f[6], "nice": f[1], "idle": f[3] + f[4], "steal": f[7]}


def _rq(x: float) -> tuple[float, int]:
    """(ms waited on a run queue, times switched in) from rq()'s packed difference."""
    k = round(x / 1e3)
    return round((x - k * 1e3) * 1e3, 3), k


def _pcts(xs: list[float]) -> list[float]:
    if not xs:
        return []
    return [round(xs[len(xs) // 2], 3), round(xs[min(len(xs) - 1, int(len(xs) * 0.99))], 3), round(xs[-1], 3)]


if __name__ == "__main__":
    sys.exit(main())
