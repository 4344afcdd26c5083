"""Issue 7, item 4: overload soak.  64 performers at 120 Hz each, served by a nearest-neighbour
filler over twelve real walks (a batched step for 64 streams costs several times the 4 ms budget;
with six walks a quiet machine kept up with most of the load and the overload check below
became a coin toss), for SOAK_S seconds, against the real daemon process.

The daemon runs with ``overdue = "serve"`` (late frames are filled, not answered `overdue`): the
point here is the overload path (degrade, conflate, count), and on a starved machine the
default deadline would answer every frame `overdue` before the model is reached;
bench/reliability_soak.py runs the default.

What must hold, and how it is checked:
* the daemon was really overloaded: most served frames were degraded (hold-last-value instead of
  the model), and on a busy machine it also conflated (dropped) frames;
* every drop is counted: each frame sent got exactly one answer (fill or drop) and the
  daemon's counters agree (frames_in = frames_out + dropped, client and daemon alike);
* nothing is left pending: once the load stops, every frame the daemon took in is served or
  dropped (polled until the counters agree);
* memory is flat: the daemon's RSS (from /proc) after the first quarter grows by less than
  RSS_GROWTH_KIB to the end.

No wall-clock figure is asserted here (a descheduled process on a shared machine overruns any
budget): the daemon's processing time against its 4 ms budget, the p99 tail, and whether the
last third of the soak is slower than the first (a queue) are measured and checked by
bench/reliability_soak.py (`--check`), which runs this same soak; docs/RELIABILITY.md has the
figures.  The bench also runs it starved (``soak(..., starve_duty=...)``: the daemon stopped and
continued during the load) and judges memory there (``rss_checks``).
"""
from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest
from reliability_daemon import Daemon, Sockets, status, write_config
from waiting import wait_until

from clients import loadgen
from mocap.baselines import NearestNeighbourModel
from mocap.datasets import SUBJECT35_WALKS, load_trial

N_STREAMS = 64
RATE_HZ = 120.0
SOAK_S = 20.0
BUDGET_MS = 4.0
RSS_GROWTH_KIB = 8 * 1024
ANSWER_WAIT_S = 30.0  # the load generator waits up to this long after its last send for the answers still out
P99_BOUND_MS = 250.0  # (bench/reliability_soak.py --check) far above any budget, far below a 20 s queue's
RSS_RISE_KIB = 64 * 1024  # (bench/reliability_soak.py --check) RSS at most this far above its first sample
STARVE_PERIOD_S = 0.05  # a starved soak stops and continues the daemon on this period (--starved)


def starve(pid: int, duty: float, seconds: float, start: threading.Event, stop: threading.Event) -> None:
    """From ``start`` on, for ``seconds``: let process ``pid`` run ``duty`` of every
    STARVE_PERIOD_S and hold it stopped (SIGSTOP) for the rest, as a CPU quota or a machine busy
    with other work would; it is always continued at the end."""
    start.wait()
    end = time.monotonic() + seconds
    try:
        while not stop.is_set() and time.monotonic() < end:
            os.kill(pid, signal.SIGSTOP)
            stop.wait(STARVE_PERIOD_S * (1.0 - duty))
            os.kill(pid, signal.SIGCONT)
            stop.wait(STARVE_PERIOD_S * duty)
    except ProcessLookupError:
        return
    finally:
        try:
            os.kill(pid, signal.SIGCONT)
        except ProcessLookupError:
            pass


def soak(tmp_path, n_streams=N_STREAMS, rate_hz=RATE_HZ, seconds=SOAK_S, budget_ms=BUDGET_MS, n_train=12,
         sample_s=0.5, overdue: str | None = None, starve_duty: float | None = None) -> dict:
    """Run one soak; returns the load result, daemon status before/after and the RSS samples.
    ``overdue``: the daemon's policy for a frame read past its budget (None: the default, drop).
    ``starve_duty``: the daemon is starved while the load runs (``starve``: it runs this share of
    the time), then given the CPU back for the load generator's wait for the last answers."""
    seqs = [load_trial(t).frames for t in SUBJECT35_WALKS[1:1 + n_train]]
    channels = list(load_trial("35_01").channels)
    NearestNeighbourModel.fit(seqs, channels).save(str(tmp_path / "nn.npz"))
    ep = write_config(tmp_path / "lacuna.toml", {"nn": {"file": "nn.npz"}}, daemon={"budget_ms": budget_ms, **({"overdue": overdue} if overdue else {})})
    d = Daemon(tmp_path / "lacuna.toml", tmp_path / "daemon.log").start()
    S = Sockets()
    rss: list[tuple[float, int]] = []
    stop = threading.Event()

    def sample() -> None:
        t0 = time.perf_counter()
        while not stop.is_set():
            rss.append((time.perf_counter() - t0, d.rss_kib()))
            stop.wait(sample_s)

    try:
        motion = load_trial("35_01").frames.astype(np.float32)  # a walk the model was not fitted on
        missing = np.zeros(motion.shape[1], bool)
        missing[[9, 10, 11, 27, 28, 29]] = True  # a knee and an elbow lose their markers
        frames = loadgen.make_frames(2400, motion.shape[1], missing, np.random.default_rng(0), motion)
        before = status(S, ep["router"])
        cpu0 = d.cpu_s()
        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        loading = threading.Event()
        starver = None
        if starve_duty is not None:
            starver = threading.Thread(target=starve, args=(d.pid, starve_duty, 0.5 + seconds, loading, stop), daemon=True)
            starver.start()
        loading.set()
        # (an answer still missing ANSWER_WAIT_S after the last send counts as lost: long enough
        # for a daemon that gets a sliver of a loaded machine to clear what it has read)
        res = loadgen.run_load(ep["router"], None, frames, n_streams=n_streams, rate=rate_hz, seconds=seconds,
                               warmup_s=0.5, drain_s=ANSWER_WAIT_S, progress=False)
        stop.set()
        sampler.join(5)
        if starver is not None:
            starver.join(5)
        cpu = d.cpu_s() - cpu0

        def settled() -> dict | None:  # nothing is pending in the daemon
            st = status(S, ep["router"])
            c = st["counters"]
            dropped = sum(v for k, v in c.items() if k.startswith("dropped_"))
            return st if c.get("frames_in", 0) == c.get("frames_out", 0) + dropped else None

        after = wait_until(settled, 10, "every frame the daemon took in to be served or dropped", 0.1)
        alive = d.alive()
        return {"res": res, "before": before, "after": after, "rss": rss, "daemon_cpu_s": cpu, "alive": alive,
                "log_bytes": (tmp_path / "daemon.log").stat().st_size}
    finally:
        stop.set()
        S.close()
        d.stop()


def thirds(a) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, dtype=np.float64)
    k = len(a) // 3
    return a[:k], a[len(a) - k:]


def pct(a, q: float) -> float:
    """Percentile q of a, NaN when a is empty (a short soak on a starved machine may serve nothing)."""
    a = np.asarray(a, dtype=np.float64)
    return float(np.percentile(a, q)) if a.size else float("nan")


def summary(r: dict) -> dict:
    res = r["res"]
    proc = np.asarray(res.proc_us) / 1e3
    rtt = np.asarray(res.rtt_s) * 1e3
    rss = np.asarray([v for _, v in r["rss"]])
    q = len(rss) // 4
    c = r["after"]["counters"]
    return {
        "offered_per_s": res.sent / res.seconds, "served_per_s": res.served / res.seconds, "sent": res.sent,
        "served": res.served, "degraded": res.degraded, "dropped": res.dropped, "lost": res.lost,
        "errors": res.errors, "unsent": getattr(res, "unsent", 0),
        "proc_p50_ms": pct(proc, 50), "proc_p99_ms": pct(proc, 99),
        "proc_max_ms": pct(proc, 100), "proc_within_budget": float((proc <= BUDGET_MS).mean()) if proc.size else float("nan"),
        "rtt_p50_ms": pct(rtt, 50), "rtt_p99_ms": pct(rtt, 99),
        "proc_p50_first_third_ms": pct(thirds(proc)[0], 50),
        "proc_p50_last_third_ms": pct(thirds(proc)[1], 50),
        "rtt_p50_first_third_ms": pct(thirds(rtt)[0], 50),
        "rtt_p50_last_third_ms": pct(thirds(rtt)[1], 50),
        "rss_start_kib": int(rss[0]), "rss_quarter_kib": int(rss[q]), "rss_end_kib": int(rss[-1]),
        "rss_max_kib": int(rss.max()), "daemon_cpu_s": r["daemon_cpu_s"], "seconds": res.seconds,
        "daemon_frames_in": c.get("frames_in", 0), "daemon_frames_out": c.get("frames_out", 0),
        "daemon_dropped": sum(v for k, v in c.items() if k.startswith("dropped_")),
        "daemon_degraded": c.get("degraded", 0), "daemon_log_bytes": r["log_bytes"],
    }


@pytest.mark.slow
def test_overload_soak_answers_every_frame_counts_every_drop_memory_flat(tmp_path, data):
    # overdue = "serve": with the default ("drop") a daemon that gets a sliver of a loaded machine
    # reads every frame past its 4 ms budget and answers them all `overdue` (seen: 0 of 153,600
    # served), which is the deadline's behaviour, not the overload's; bench/reliability_soak.py
    # measures the default
    r = soak(tmp_path, overdue="serve")
    s = summary(r)
    print("\nsoak: " + ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in s.items()))
    assert r["alive"]
    res = r["res"]
    # overloaded: most frames could only be served by the cheaper path (on a quiet machine the
    # degraded path keeps up and nothing is conflated; on a busy one frames are also dropped)
    assert s["served"] > 0 and s["degraded"] > 0.5 * s["served"]
    # every frame got exactly one answer, and both sides count the same
    assert s["lost"] == 0 and s["errors"] == 0
    assert s["sent"] == s["served"] + s["dropped"]
    assert s["daemon_frames_in"] == s["daemon_frames_out"] + s["daemon_dropped"]
    warm = r["before"]["counters"]
    assert s["daemon_frames_in"] - warm.get("frames_in", 0) >= s["sent"]  # (+ the unmeasured warm-up)
    # every served frame carries the daemon's processing time (its figures: bench/reliability_soak.py)
    assert len(res.proc_us) == s["served"] and min(res.proc_us) >= 0
    # memory flat after the first quarter
    assert s["rss_end_kib"] - s["rss_quarter_kib"] < RSS_GROWTH_KIB


def rss_checks(s: dict) -> dict[str, bool]:
    """Memory bounds for bench/reliability_soak.py --check, starved or not: flat after the first
    quarter (as the test asserts) and never far above the first sample (a backlog held in the
    daemon, in Python or in libzmq, would lift it: 130 -> 354 MB before the lossless inputs' queue
    was bounded, bench/notebook/immut.md)."""
    return {
        f"RSS end - first quarter < {RSS_GROWTH_KIB >> 10} MiB": s["rss_end_kib"] - s["rss_quarter_kib"] < RSS_GROWTH_KIB,
        f"RSS max - start < {RSS_RISE_KIB >> 10} MiB": s["rss_max_kib"] - s["rss_start_kib"] < RSS_RISE_KIB,
    }


def timing_checks(s: dict) -> dict[str, bool]:
    """The soak's wall-clock bounds, for bench/reliability_soak.py --check (not asserted by the test):
    served frames within budget, a bounded tail, and no queue (the last third no slower than
    twice the first)."""
    return {
        f"proc p50 <= budget {BUDGET_MS:g} ms": s["proc_p50_ms"] <= BUDGET_MS,
        f"proc p99 <= {P99_BOUND_MS:g} ms": s["proc_p99_ms"] <= P99_BOUND_MS,
        "proc p50, last third <= 2x first third": s["proc_p50_last_third_ms"] <= max(2 * s["proc_p50_first_third_ms"], BUDGET_MS),
        "rtt p50, last third <= 2x first third": s["rtt_p50_last_third_ms"] <= max(2 * s["rtt_p50_first_third_ms"], 2 * 1000 / RATE_HZ),
    }
