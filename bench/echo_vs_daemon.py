"""The daemon against a bare two-process ZeroMQ echo, driven by the same client, A/B across code trees.

Issue 19's targets, measured in one run, alternating, on one machine:

* one stream at 120 Hz: the round trip of a bare pyzmq ROUTER echo (bench/zmq_echo.py, a
  separate process) and of the daemon's pass-through and HLM, with the same load generator
  (clients.loadgen) and the same frames; p50/p99 and the ratios daemon/echo, hlm/pass-through;
* 64 performers x 120 Hz bundled (one ``frames`` message a tick, one connection): the daemon's
  CPU per frame (/proc utime+stime over the run / frames sent to it; ``cpu_us_per_frame_served``
  divides by the frames served instead) for pass-through and HLM, and
  the frames dropped as overdue, beside the echo's own CPU per frame and drops.

Every code tree given with ``--root NAME=DIR`` (default: this checkout as ``new``) runs its own
``lacuna serve`` subprocess (PYTHONPATH=DIR, so its own daemon package) and its own HLM, trained
in that tree by its own ``hlm.methods.train_model`` on CMU 35_01, 35_06, 35_07 (3 EM iterations,
1 restart, 2 styles: a small real model, cached under --cache).  The frames are CMU 35_08 with
the left arm missing (35_08 is not in the model's training takes).  Within a repeat each tree's
daemon runs right after an echo run, and the trees' order rotates from repeat to repeat.

    git worktree add --detach /tmp/perf-64e7005 64e7005
    git worktree add --detach /tmp/perf-main main
    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python bench/echo_vs_daemon.py \\
        --root new=. --root main=/tmp/perf-main --root old=/tmp/perf-64e7005 \\
        --seconds 10 --repeats 3 --json bench/results/echo_vs_daemon.json

The PNG (beside the JSON) holds the one-stream round-trip histograms.  Progress goes to stderr.
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
sys.path.insert(0, str(ROOT))

from bench.zmq_echo import ECHO  # noqa: E402
from clients import loadgen  # noqa: E402
from clients.client import control  # noqa: E402
from clients.configfile import free_port, write_config  # noqa: E402
from clients.harness import cpu_seconds  # noqa: E402
from clients.session import DaemonUnavailable  # noqa: E402

TRAIN = ("35_01", "35_06", "35_07")
TEST = "35_08"
MISSING = ("lhumerus", "lradius", "lwrist", "lhand")
TRAIN_HLM = r'''
import sys
from hlm.methods import train_model
from mocap.datasets import load_trial
train = [load_trial(t) for t in sys.argv[2].split(",")]
import json
# (--hlm-option: a tree whose train_model does not know an option ignores it, as hlm.methods does)
model = train_model([m.frames for m in train], list(train[0].channels), n_iter=3, restarts=1, styles=2,
                    **json.loads(sys.argv[3]))
model.save(sys.argv[1])
'''


def tree_env(root: Path) -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=str(root), PYTHONUNBUFFERED="1", OPENBLAS_NUM_THREADS="1")


def tree_roots(specs: list[str]) -> dict[str, Path]:
    """``--root NAME=DIR`` options -> {NAME: DIR}; none: this checkout as ``new``."""
    return {s.split("=", 1)[0]: Path(s.split("=", 1)[1]).resolve() for s in (specs or [f"new={ROOT}"])}


def rotated(names: list[str], k: int) -> list[str]:
    """The trees' order in repeat k: rotated by k, so no tree always runs first."""
    return names[k % len(names):] + names[:k % len(names)]


def tree_hlm(root: Path, cache: Path, options: dict[str, Any] | None = None) -> Path:
    """The HLM file of this tree (trained by its own code once, then cached by commit and ``options``,
    extra keyword arguments of ``hlm.methods.train_model``)."""
    rev = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                         text=True, check=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--", "hlm"], check=False,
                           capture_output=True,
                           text=True).stdout.strip()
    opts = "".join(f"-{k}={v}" for k, v in sorted((options or {}).items()))
    out = cache / f"hlm-{rev}{'-dirty' if dirty else ''}{opts}.npz"
    if not out.exists():
        print(f"training the HLM of {root} ({rev}) ...", file=sys.stderr, flush=True)
        subprocess.run([sys.executable, "-c", TRAIN_HLM, str(out), ",".join(TRAIN), json.dumps(options or {})],
                       cwd=root, env=tree_env(root),
                       check=True)
    return out


class Served:
    """One tree's ``lacuna serve`` with models floor (pass-through) and hlm (unless None) on the same channels."""

    def __init__(self, root: Path, hlm: Path | None, channels: list[str], workdir: Path, budget_ms: float):
        self.endpoint = f"tcp://127.0.0.1:{free_port()}"
        cfg = workdir / "lacuna.toml"
        models: dict[str, Any] = {"models.floor": {"builtin": "passthrough", "channels": channels}}
        if hlm is not None:
            models["models.hlm"] = {"file": str(hlm)}
        write_config(cfg, {"daemon": {"default_model": "floor", "budget_ms": budget_ms, "max_streams": 4096,
                                      "log_level": "warning"},
                           "zmq": {"router": self.endpoint}, **models})
        self.log = open(workdir / "daemon.log", "ab")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen([sys.executable, "-m", "lacuna.cli", "serve", "--config", str(cfg)], cwd=root,
                                     env=tree_env(root), stdin=subprocess.DEVNULL, stdout=self.log, stderr=self.log)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"{root}: the daemon exited: {(workdir / 'daemon.log').read_text()[-2000:]}")
            try:
                control(self.endpoint, "status", timeout_s=0.5)
                return
            except DaemonUnavailable:
                time.sleep(0.1)
        self.stop()
        raise RuntimeError(f"{root}: the daemon did not answer")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(15)
        self.log.close()


class Echo:
    def __init__(self) -> None:
        self.endpoint = f"tcp://127.0.0.1:{free_port()}"
        self.proc = subprocess.Popen([sys.executable, "-c", ECHO, self.endpoint], stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None and self.proc.stdout.readline().strip() == "ready"

    def stop(self) -> None:
        self.proc.kill()
        self.proc.wait(15)


def run(endpoint: str, pid: int, case: str, model: str | None, prefix: str, channels: list[str], frames: np.ndarray,
        observed: np.ndarray, seconds: float, rate: float, budget_ms: float = 4.0) -> tuple[dict[str, Any], np.ndarray]:
    bundled = case == "bundled"
    n = 64 if bundled else 1
    c0 = cpu_seconds(pid)
    res = loadgen.run_load(endpoint, channels, frames, observed, n_streams=n, rate=rate, seconds=seconds, model=model,
                           prefix=prefix, progress=False, connections=1 if bundled else None, bundle=bundled)
    c1 = cpu_seconds(pid)
    row = {**loadgen.percentiles(res.rtt_ms), "sent": res.sent, "served": res.served, "dropped": res.dropped,
           "overdue": int(res.drop_reasons.get("overdue", 0)), "drop_reasons": res.drop_reasons,
           "errors": res.errors, "lost": res.lost, "unsent": res.unsent,
           # answers that came back later than the daemon's budget, seen from the client: for the echo, the
           # frames the machine itself would have made late (its stalls), beside the daemon's overdue drops
           "rtt_over_budget": int((np.asarray(res.rtt_ms) > budget_ms).sum()),
           # per frame the process received (served or dropped: a dropped frame costs its decode too)
           "cpu_us_per_frame": (1e6 * (c1 - c0) / max(1, res.sent)) if c0 is not None and c1 is not None else None,
           "cpu_us_per_frame_served": (1e6 * (c1 - c0) / max(1, res.served)) if c0 is not None and c1 is not None
           else None}
    return row, res.rtt_ms


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--root", action="append", default=[], metavar="NAME=DIR", help="a code tree to serve (repeatable)")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=120.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--budget-ms", type=float, default=4.0, help="the daemons' budget_ms (the default config's)")
    ap.add_argument("--cases", default="single,bundled")
    ap.add_argument("--models", default="floor,hlm")
    ap.add_argument("--hlm-option", action="append", default=[], metavar="KEY=VALUE",
                    help="a keyword of hlm.methods.train_model (JSON value) for every tree's HLM, e.g. cond_shrink=0 "
                         "(the HLM as `lacuna train default` trains its expert); a tree that does not know it ignores it")
    ap.add_argument("--cache", default=os.path.join(tempfile.gettempdir(), "lacuna-echo-vs-daemon"))
    ap.add_argument("--json", dest="json_out", default=str(ROOT / "bench/results/echo_vs_daemon.json"))
    args = ap.parse_args(argv)
    from mocap.datasets import load_trial

    roots = tree_roots(args.root)
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    test = load_trial(TEST)
    channels = list(load_trial(TRAIN[0]).channels)
    frames = test.frames[:, test.index(channels)].astype(np.float32)
    observed = np.broadcast_to(~np.array([c.split(".")[0] in MISSING for c in channels]), frames.shape).copy()
    hopts = {k: json.loads(v) for k, v in (x.split("=", 1) for x in args.hlm_option)}
    hlms = {name: tree_hlm(root, cache, hopts) for name, root in roots.items()} if "hlm" in args.models else {}
    models = args.models.split(",")
    cases = args.cases.split(",")
    rows: list[dict[str, Any]] = []
    rtts: dict[str, list[np.ndarray]] = {}
    for rep in range(args.repeats):
        order = rotated(list(roots), rep)
        for name in order:
            work = Path(tempfile.mkdtemp(prefix=f"evd-{name}-", dir=cache))
            d = Served(roots[name], hlms.get(name, next(iter(hlms.values()), None)), channels, work, args.budget_ms)
            try:
                for case in cases:
                    e = Echo()
                    try:
                        row, rt = run(e.endpoint, e.proc.pid, case, None, f"echo{rep}{name}{case}", channels, frames,
                                      observed, args.seconds, args.rate, args.budget_ms)
                    finally:
                        e.stop()
                    rows.append({"repeat": rep, "target": "echo", "before": name, "case": case, **row})
                    rtts.setdefault(f"{case} echo", []).append(rt)
                    _say(rows[-1])
                    for model in models:
                        row, rt = run(d.endpoint, d.proc.pid, case, model, f"{name}{rep}{model}{case}", channels,
                                      frames, observed, args.seconds, args.rate, args.budget_ms)
                        rows.append({"repeat": rep, "target": f"{name}:{model}", "case": case, **row})
                        rtts.setdefault(f"{case} {name}:{model}", []).append(rt)
                        _say(rows[-1])
            finally:
                d.stop()
    summary = summarise(rows, list(roots), models, cases)
    out = {"command": "python bench/echo_vs_daemon.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "roots": {k: {"dir": str(v), "commit": _rev(v)} for k, v in roots.items()},
           "frames": f"CMU {TEST}, left arm ({', '.join(MISSING)}) missing; HLM trained on {', '.join(TRAIN)}",
           "seconds": args.seconds, "rate": args.rate, "repeats": args.repeats, "budget_ms": args.budget_ms,
           "hlm_options": hopts, "at": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "loadavg": os.getloadavg(),
           "summary": summary, "runs": rows}
    print(json.dumps(summary, indent=1))
    Path(args.json_out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json_out).write_text(json.dumps(out, indent=1))
    plot(rtts, Path(args.json_out).with_suffix(".png"))
    return 0


def _rev(root: Path) -> str:
    r = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, check=False)
    dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True, check=False).stdout.strip()
    return r.stdout.strip() + (" (uncommitted changes)" if dirty else "")


def _say(r: dict[str, Any]) -> None:
    cpu = r["cpu_us_per_frame"]
    print(f"repeat {r['repeat']} {r['case']:>7} {r['target']:>12}: p50 {r['p50_ms'] or float('nan'):.3f} "
          f"p99 {r['p99_ms'] or float('nan'):.3f} ms, CPU {cpu if cpu is not None else float('nan'):.1f} us/frame, "
          f"served {r['served']}/{r['sent']}, overdue {r['overdue']}, dropped {r['dropped']}, "
          f"{r.get('rtt_over_budget')} answered after the budget",
          file=sys.stderr, flush=True)


def summarise(rows: list[dict[str, Any]], roots: list[str], models: list[str], cases: list[str]) -> dict[str, Any]:
    """Medians over repeats; each ratio to the echo uses the echo run just before that tree's daemon."""
    out: dict[str, Any] = {}
    for case in cases:
        cs: dict[str, Any] = {}
        for name in roots:
            for model in models:
                mine = [r for r in rows if r["case"] == case and r["target"] == f"{name}:{model}"]
                echo = {r["repeat"]: r for r in rows if r["case"] == case and r["target"] == "echo" and r["before"] == name}
                floor = {r["repeat"]: r for r in rows if r["case"] == case and r["target"] == f"{name}:floor"}
                s: dict[str, Any] = {k: _med([r[k] for r in mine]) for k in ("p50_ms", "p99_ms", "cpu_us_per_frame")}
                s["overdue"] = [r["overdue"] for r in mine]
                s["dropped"] = [r["dropped"] for r in mine]
                s["rtt_over_budget"] = [r.get("rtt_over_budget") for r in mine]
                for q in ("p50_ms", "p99_ms"):
                    s[f"{q}_over_echo"] = _med([_div(r[q], echo[r["repeat"]][q]) for r in mine])
                    if model != "floor" and floor:  # (none: --models without floor)
                        s[f"{q}_over_passthrough"] = _med([_div(r[q], floor[r["repeat"]][q]) for r in mine])
                cs[f"{name}:{model}"] = s
        ech = [r for r in rows if r["case"] == case and r["target"] == "echo"]
        cs["echo"] = {k: _med([r[k] for r in ech]) for k in ("p50_ms", "p99_ms", "cpu_us_per_frame")}
        cs["echo"]["dropped"] = [r["dropped"] for r in ech]
        cs["echo"]["rtt_over_budget"] = [r.get("rtt_over_budget") for r in ech]
        for name in roots[1:]:  # the first tree's CPU per frame over each other tree's, pairing repeats
            for model in models:
                a = {r["repeat"]: r for r in rows if r["case"] == case and r["target"] == f"{roots[0]}:{model}"}
                b = {r["repeat"]: r for r in rows if r["case"] == case and r["target"] == f"{name}:{model}"}
                cs[f"cpu_{roots[0]}_over_{name}:{model}"] = _med(
                    [_div(a[k]["cpu_us_per_frame"], b[k]["cpu_us_per_frame"]) for k in a if k in b])
        out[case] = cs
    return out


def _div(a: float | None, b: float | None) -> float | None:
    return None if a is None or not b else a / b


def _med(xs: list[float | None]) -> float | None:
    v = [x for x in xs if x is not None]
    return float(np.median(v)) if v else None


def plot(rtts: dict[str, list[np.ndarray]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [k for k in rtts if k.startswith("single ")]
    if not keys:
        return
    fig, ax = plt.subplots(figsize=(9, 5))
    allv = np.concatenate([np.concatenate(rtts[k]) for k in keys])
    bins = np.logspace(np.log10(max(0.02, allv.min())), np.log10(allv.max() + 1e-9), 80)
    for k in keys:
        v = np.concatenate(rtts[k])
        ax.hist(v, bins=bins, histtype="step", lw=1.4,
                label=f"{k[7:]}: p50 {np.median(v):.3f} p99 {np.percentile(v, 99):.3f} ms (n={v.size})")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("round trip, ms (one stream, 120 Hz, loopback)")
    ax.set_ylabel("frames")
    ax.set_title("bare pyzmq echo vs daemon, same client (all repeats pooled)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
