"""Where one stream's extra time goes in the daemon, frame by frame: pass-through against HLM.

The daemon is a real ``lacuna serve`` process (this tree's, or ``--root``'s) with the same config
and frames as bench/echo_vs_daemon.py's one-stream case (CMU 35_08, left arm missing; the HLM
trained there on 35_01/06/07), driven by the same client (clients.loadgen, 1 stream, 120 Hz);
pass-through and HLM take turns on one daemon, repeat by repeat.  The daemon process is started
through a bootstrap that wraps, with perf_counter stamps kept in lists and written at exit (the
daemon's own code is not changed):

* ``Transports.poll``: when the loop went to sleep, with which timeout, when it woke;
* ``Scheduler.run``: each served frame's receipt time (``arrived``), the step's start and end;
* ``Tick._answer``: the end of the fills' encoding and sending;
* ``Prewarm.rehearse``: each rehearsal's start and end (and the calls that found nothing to rehearse);
* ``gc.callbacks``: every collection's generation, start and end.

Per frame: ``pre`` = receipt -> step start (decode, session, plan), ``step``, ``post`` = step end ->
sent, ``proc`` = receipt -> sent; ``wake`` = poll return -> receipt is not known (the receipt is
stamped right after the read), so beside them the client's round trip minus ``proc``.  For each
model it prints percentiles of each part, and for HLM's slowest frames (the round trip's top 2%)
what they had in common: a rehearsal running when the frame was read (collision), how long
before it the last rehearsal ended, a collection during the frame.

    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python bench/hlm_tail.py [--root new=. --root old=DIR] --seconds 8 --repeats 2 \\
        --json bench/results/hlm_tail.json
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
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
STAMP_S = 50e-6  # a receipt this close before a rehearsal's traced start is that rehearsal's start stamp
sys.path.insert(0, str(ROOT))

from bench.echo_vs_daemon import MISSING, TEST, TRAIN, tree_env, tree_hlm, tree_roots  # noqa: E402
from clients import loadgen  # noqa: E402
from clients.client import control  # noqa: E402
from clients.configfile import free_port, write_config  # noqa: E402
from clients.session import DaemonUnavailable  # noqa: E402

BOOT = r'''
import gc, json, os, sys, time
T = time.perf_counter
rec = {"poll": [], "step": [], "answer": [], "rh": [], "rh_idle": [], "due": [], "gc": []}
from daemon import transport, scheduler, tick, prewarm, loop
_poll = transport.Transports.poll
def poll(self, timeout):
    t0 = T(); r = _poll(self, timeout); rec["poll"].append((t0, timeout, T(), bool(r))); return r
transport.Transports.poll = poll
_run = scheduler.Scheduler.run
def run(self, groups, now):
    arr = [s.pending.arrived for _, ss in groups.values() for s in ss]
    names = [s.model_name for _, ss in groups.values() for s in ss]
    t0 = T(); r = _run(self, groups, now); t1 = T()
    rec["step"].append((min(arr) if arr else 0.0, t0, t1, len(arr), names[0] if names else ""))
    return r
scheduler.Scheduler.run = run
_ans = tick.Tick._answer
def answer(self, results, t0):
    r = _ans(self, results, t0); rec["answer"].append(T()); return r
tick.Tick._answer = answer
_rh = prewarm.Prewarm.rehearse
def rehearse(self, *a, **k):
    c = self.count; t0 = T(); r = _rh(self, *a, **k)
    if self.count > c:
        rec["rh"].append((t0, T()))
    else:
        rec["rh_idle"].append(t0)
    return r
prewarm.Prewarm.rehearse = rehearse
_srv = prewarm.Prewarm.served
def served(self, s, frame, arrived, sched):
    r = _srv(self, s, frame, arrived, sched); rec["due"].append((arrived, self.due)); return r
prewarm.Prewarm.served = served
_gc0 = [0.0]
def cb(phase, info):
    if phase == "start":
        _gc0[0] = T()
    else:
        rec["gc"].append((info["generation"], _gc0[0], T()))
gc.callbacks.append(cb)
try:
    loop.serve(sys.argv[1])
finally:
    with open(os.environ["HLM_TAIL_OUT"], "w") as f:
        json.dump(rec, f)
'''


class Traced:
    """A ``lacuna serve`` of ``root`` (models floor and hlm) started through BOOT."""

    def __init__(self, root: Path, hlm: Path, channels: list[str], work: Path, extra: dict[str, Any]):
        self.endpoint = f"tcp://127.0.0.1:{free_port()}"
        self.out = work / "trace.json"
        cfg = work / "lacuna.toml"
        write_config(cfg, {"daemon": {"default_model": "floor", "budget_ms": 4.0, "max_streams": 4096,
                                      "log_level": "warning", **extra},
                           "zmq": {"router": self.endpoint},
                           "models.floor": {"builtin": "passthrough", "channels": channels},
                           "models.hlm": {"file": str(hlm)}})
        self.log = open(work / "daemon.log", "ab")  # noqa: SIM115 - closed in stop()
        env = dict(tree_env(root), HLM_TAIL_OUT=str(self.out))
        self.proc = subprocess.Popen([sys.executable, "-c", BOOT, str(cfg)], cwd=root, env=env,
                                     stdin=subprocess.DEVNULL, stdout=self.log, stderr=self.log)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"the daemon exited: {(work / 'daemon.log').read_text()[-2000:]}")
            try:
                control(self.endpoint, "status", timeout_s=0.5)
                return
            except DaemonUnavailable:
                time.sleep(0.1)
        self.stop()
        raise RuntimeError("the daemon did not answer")

    def stop(self) -> dict[str, Any]:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(15)
        self.log.close()
        return json.loads(self.out.read_text()) if self.out.exists() else {}


def frames_of(rec: dict[str, Any], model: str) -> list[dict[str, float]]:
    """Per served frame of ``model``: its parts (us) and what was around it."""
    steps = [s for s in rec["step"] if s[4] == model and s[3] == 1]
    ans = np.array(rec["answer"])
    rh = np.array(rec["rh"]) if rec["rh"] else np.zeros((0, 2))
    gcs = rec["gc"]
    out = []
    prev = -np.inf
    for arrived, t0, t1, _, _ in steps:
        # a rehearsal since this stream's previous step, before this frame was read
        ahead = bool(rh.size and ((rh[:, 0] > prev) & (rh[:, 0] < arrived)).any())
        prev = t1
        k = np.searchsorted(ans, t1)
        sent = float(ans[k]) if k < ans.size else np.nan
        # the last rehearsal that started before the frame was read
        j = np.searchsorted(rh[:, 0], arrived) - 1 if rh.size else -1
        r0, r1 = (rh[j] if j >= 0 else (np.nan, np.nan))
        collide = bool(j >= 0 and r1 > arrived)
        if not collide and j + 1 < len(rh) and rh[j + 1, 0] - arrived < STAMP_S and rh[j + 1, 1] <= t0:
            # the daemon stamps what landed during a rehearsal with the rehearsal's start
            # (daemon/wait.py), taken just before the traced start: a frame stamped so waited for it
            j += 1
            r0, r1 = rh[j]
            collide = True
        g = [x for x in gcs if x[2] > arrived and x[1] < sent]
        out.append({"arrived": arrived, "pre": (t0 - arrived) * 1e6, "step": (t1 - t0) * 1e6, "post": (sent - t1) * 1e6,
                    "proc": (sent - arrived) * 1e6, "rh_before_us": (arrived - r1) * 1e6 if j >= 0 else np.nan,
                    "rh_us": (r1 - r0) * 1e6 if j >= 0 else np.nan, "collide": collide,
                    "rh_wait_us": max(0.0, (r1 - arrived) * 1e6) if collide else 0.0,
                    "rehearsed": ahead, "gc_us": sum((x[2] - x[1]) * 1e6 for x in g), "gc_gen": max((x[0] for x in g), default=-1)})
    return out


def pct(v: list[float] | np.ndarray) -> dict[str, float]:
    a = np.asarray(v, dtype=float)
    a = a[np.isfinite(a)]
    if not a.size:
        return {}
    return {"p50": float(np.median(a)), "p90": float(np.percentile(a, 90)), "p99": float(np.percentile(a, 99)),
            "max": float(a.max())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--root", action="append", default=[], metavar="NAME=DIR",
                    help="a code tree (repeatable: trees take turns, repeat by repeat; default this one as new)")
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--prewarm-ms", type=float, help="the daemons' prewarm_ms (default: the config's default)")
    ap.add_argument("--cache", default=os.path.join(tempfile.gettempdir(), "lacuna-echo-vs-daemon"))
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args(argv)
    from mocap.datasets import load_trial

    roots = tree_roots(args.root)
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    test = load_trial(TEST)
    channels = list(load_trial(TRAIN[0]).channels)
    frames = test.frames[:, test.index(channels)].astype(np.float32)
    observed = np.broadcast_to(~np.array([c.split(".")[0] in MISSING for c in channels]), frames.shape).copy()
    hlm = tree_hlm(next(iter(roots.values())), cache)  # (one model file for every tree: the same bits in)
    extra = {} if args.prewarm_ms is None else {"prewarm_ms": args.prewarm_ms}
    keys = [f"{n}:{m}" for n in roots for m in ("floor", "hlm")]
    per: dict[str, list[dict[str, float]]] = {k: [] for k in keys}
    rows = []
    for rep, name in [(r, n) for r in range(args.repeats)
                      for n in (list(roots)[r % len(roots):] + list(roots)[:r % len(roots)])]:
        work = Path(tempfile.mkdtemp(prefix="hlmtail-", dir=cache))
        d = Traced(roots[name], hlm, channels, work, extra)
        order = ["floor", "hlm"] if rep % 2 == 0 else ["hlm", "floor"]
        got: dict[str, Any] = {}
        try:
            for model in order:
                res = loadgen.run_load(d.endpoint, channels, frames, observed, n_streams=1, rate=120.0,
                                       seconds=args.seconds, model=model, prefix=f"t{rep}{name}{model}",
                                       progress=False)
                got[model] = res
        finally:
            rec = d.stop()
        for model in order:
            fr = frames_of(rec, model)
            res = got[model]
            rt = res.rtt_ms * 1e3
            if len(fr) == rt.size:
                for f, r in zip(fr, rt):
                    f["rtt"] = float(r)
                    f["outside"] = float(r - f["proc"])
            per[f"{name}:{model}"] += fr
            rows.append({"repeat": rep, "tree": name, "model": model, "trace": str(d.out), "rtt_p50_us": float(np.median(rt)),
                         "rtt_p99_us": float(np.percentile(rt, 99)), "frames": len(fr), "served": res.served,
                         "gc": [sum(1 for g in rec["gc"] if g[0] == k) for k in range(3)],
                         "rehearsals": len(rec["rh"]), "rehearse_idle": len(rec["rh_idle"])})
            print(f"repeat {rep} {name}:{model:>5}: rtt p50 {rows[-1]['rtt_p50_us']:.0f} p99 {rows[-1]['rtt_p99_us']:.0f} us, "
                  f"{len(fr)} frames traced of {res.served} served; gc by generation {rows[-1]['gc']}, rehearsals "
                  f"{rows[-1]['rehearsals']} (+{rows[-1]['rehearse_idle']} idle) (whole daemon)",
                  file=sys.stderr, flush=True)
    summary: dict[str, Any] = {}
    for model, fr in per.items():
        s = {k: pct([f[k] for f in fr if k in f]) for k in ("rtt", "outside", "proc", "pre", "step", "post",
                                                           "rh_before_us", "rh_us", "rh_wait_us", "gc_us")}
        s["rehearsed_share"] = float(np.mean([f["rehearsed"] for f in fr])) if fr else None
        s["step_rehearsed"] = pct([f["step"] for f in fr if f["rehearsed"]])
        s["step_not_rehearsed"] = pct([f["step"] for f in fr if not f["rehearsed"]])
        s["proc_not_rehearsed"] = pct([f["proc"] for f in fr if not f["rehearsed"]])
        s["collide_share"] = float(np.mean([f["collide"] for f in fr])) if fr else None
        s["gc_share"] = float(np.mean([f["gc_us"] > 0 for f in fr])) if fr else None
        with_rtt = [f for f in fr if "rtt" in f]
        if with_rtt:
            cut = np.percentile([f["rtt"] for f in with_rtt], 98)
            tail = [f for f in with_rtt if f["rtt"] >= cut]
            s["tail"] = {"n": len(tail), "rtt_from_us": float(cut),
                         **{k: float(np.median([f[k] for f in tail])) for k in ("outside", "proc", "pre", "step", "post",
                                                                                 "rh_before_us")},
                         "collide": int(sum(f["collide"] for f in tail)), "gc": int(sum(f["gc_us"] > 0 for f in tail))}
        summary[model] = s
    for model, s in summary.items():
        print(f"\n{model}:", file=sys.stderr)
        for k, v in s.items():
            if isinstance(v, dict):
                print(f"  {k:>13}: " + "  ".join(f"{a} {b:.0f}" if isinstance(b, float) else f"{a} {b}"
                                                 for a, b in v.items()), file=sys.stderr)
            else:
                print(f"  {k:>13}: {v}", file=sys.stderr)
    if args.json_out:
        Path(args.json_out).write_text(json.dumps({
            "command": "python bench/hlm_tail.py " + " ".join(argv if argv is not None else sys.argv[1:]),
            "roots": {k: str(v) for k, v in roots.items()}, "at": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "loadavg": os.getloadavg(), "summary": summary, "runs": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
