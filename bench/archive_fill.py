"""Batch fill throughput on Dask: takes/s and frames/s with 1 and 2 local workers and with a
scheduler + 2 workers on loopback, and where the time goes.

    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python bench/archive_fill.py \
        --model bench/out/archive_hlm.npz --takes 40 --rounds 3 --json bench/results/archive_fill.json

The batch: the first ``--takes`` locomotion takes of the data directory in name order (every
take's frames, ``--drop gaps`` erasing the gaps protocol's seeded bursts, filled with the
model's default method, ``hlm-lag`` for an HLM); takes are repeated when there are fewer.  Runs
alternate between the configurations round by round (the machine is shared), each on a fresh
output directory.  Per run: the batch's wall time from the first submit to the last result (the
cluster already up; its start is reported apart), the model's scatter, every take's own timers
(model load, read, fill, write) and Dask's task stream (compute start/stop per take on each
worker), from which the scheduling gap (a worker idle between the end of one take and the start
of its next) is measured per take, and the workers' CPU time (getrusage) over the batch.

Two rates per run: ``takes_per_s`` over the batch's wall time (cluster up; it includes the
workers' warm-up, ``archive.warmup.warm``, and the model's scatter) and ``e2e_takes_per_s`` over
that plus the cluster's start, i.e. what ``lacuna fill`` takes from the first worker process to the
last output.  ``process`` runs the batch in this process (no Dask: a worker's own cost); a
``-cold`` suffix (``local-2-cold``) skips the warm-up task (each worker's first take then pays the
imports and the model).  ``tail_s``: one worker idle at the end while the other finishes.

``loopback-N`` starts ``dask scheduler`` and N ``dask worker`` processes, each in its own session;
``local-N`` is ``lacuna fill``'s LocalCluster, whose workers share the caller's session.  On a
Linux machine with autogroup scheduling (``/proc/sys/kernel/sched_autogroup_enabled``) and other
sessions keeping the CPUs busy, a session gets one share of the CPU however many processes it
runs, so ``local-2`` gets little more CPU than ``local-1``; ``cpu_share`` says what each got.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def batch_takes(n: int) -> list[str]:
    from mocap import datasets, splits

    root = Path(datasets.data_dir(required=True))
    loco = sorted(t for t, a in splits.ACTIVITY.items() if a in ("walk", "turn", "run"))
    paths = []
    for t in loco:
        try:
            paths.append(str(splits.take_path(t)))
        except Exception:
            continue
    if not paths:
        raise SystemExit(f"no locomotion takes under {root}")
    return [paths[i % len(paths)] for i in range(n)]


def _links(paths: list[str], d: Path) -> list[str]:
    """Distinct names for repeated takes (links beside a link to their ASF)."""
    out, seen = [], {}
    for p in paths:
        k = seen.get(p, 0)
        seen[p] = k + 1
        if k == 0:
            out.append(p)
            continue
        sub = d / f"rep{k}" / Path(p).parent.name
        sub.mkdir(parents=True, exist_ok=True)
        for asf in Path(p).parent.glob("*.asf"):
            if not (sub / asf.name).exists():
                os.symlink(asf, sub / asf.name)
        os.symlink(p, sub / Path(p).name)
        out.append(str(sub / Path(p).name))
    return out


def _gaps(stream: list[dict], t_submit: float) -> dict:
    """Per worker, idle time between consecutive takes; and compute time per take."""
    by_w: dict[str, list[tuple[float, float]]] = {}
    for ev in stream:
        if "lacuna-fill" not in str(ev.get("key")):
            continue
        for ss in ev["startstops"]:
            if ss["action"] == "compute":
                by_w.setdefault(ev["worker"], []).append((ss["start"], ss["stop"]))
    gaps, comp, first, last = [], [], [], []
    for _w, iv in by_w.items():
        iv.sort()
        first.append(iv[0][0] - t_submit)
        last.append(iv[-1][1])
        comp += [b - a for a, b in iv]
        gaps += [iv[i + 1][0] - iv[i][1] for i in range(len(iv) - 1)]
    return {"tasks": len(comp), "compute_s_mean": float(np.mean(comp)) if comp else None,
            "gap_s_mean": float(np.mean(gaps)) if gaps else None, "gap_s_max": float(np.max(gaps)) if gaps else None,
            "first_start_s": float(np.mean(first)) if first else None,
            # the end: one worker idle while the other finishes its last take
            "tail_s": float(max(last) - min(last)) if last else None}


def _cpu() -> float:
    import resource

    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def run_one(kind: str, jobs_paths: list[str], spec, model: str, work: Path) -> dict:
    from dask_cluster import dask_cluster
    from distributed import get_task_stream

    from archive.batch import run_batch
    from archive.cluster import open_client
    from archive.takes import discover

    out = Path(tempfile.mkdtemp(prefix=f"{kind}-", dir=work))
    jobs = discover(jobs_paths, str(out))
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    if kind == "process":  # no Dask: run_batch in this process, the reference for a worker's own cost
        c0 = _cpu()
        res = run_batch(jobs, spec, model, None, progress=False)
        t_up, n, g, worker_cpu, client_cpu = 0.0, 1, {}, _cpu() - c0, 0.0
    else:
        n = int(kind.split("-")[1])
        loop = kind.startswith("loopback")
        cm = dask_cluster(n) if loop else open_client(None, n)
        with cm as c:
            client = c.client if loop else c
            t_up = time.perf_counter() - t0
            cpu0 = client.run(_cpu)
            c0 = _cpu()
            t_submit = time.time()
            with get_task_stream(client=client) as ts:
                res = run_batch(jobs, spec, model, client, progress=False, warm=not kind.endswith("-cold"))
            client_cpu = _cpu() - c0   # this process: the client and, for local-N, the scheduler
            stream = ts.data
            cpu1 = client.run(_cpu)
        worker_cpu = sum(cpu1[w] - cpu0[w] for w in cpu1)
        g = _gaps(stream, t_submit)
    rows = res.rows
    secs = {k: float(np.sum([r["seconds"].get(k, 0.0) for r in rows])) for k in ("model", "read", "fill", "write", "total")}
    s = res.summary()
    e2e = t_up + s["wall_s"]
    return {"config": kind, "cluster_start_s": round(t_up, 2), "wall_s": s["wall_s"], "takes": s["filled"],
            "failed": s["failed"], "frames": s["frames"], "takes_per_s": s["takes_per_s"], "frames_per_s": s["frames_per_s"],
            "e2e_wall_s": round(e2e, 3), "e2e_takes_per_s": round(s["filled"] / e2e, 3),
            "model_ship_s": s["model_ship_s"], "work_s": secs, "worker_cpu_s": round(worker_cpu, 2),
            "client_cpu_s": round(client_cpu, 2), "warm": res.warm,
            "cpu_share": round(worker_cpu / (n * s["wall_s"]), 3), "task_stream": g, "load1_before": load0,
            "load1_after": os.getloadavg()[0],
            "rehearsal_rms_deg_mean": float(np.mean([r["rehearsal"]["rms_deg"] for r in rows
                                                     if r.get("rehearsal") and r["rehearsal"]["rms_deg"] is not None]))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--method", default=None)
    ap.add_argument("--takes", type=int, default=40)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--configs", default="local-1,local-2,loopback-1,loopback-2")
    ap.add_argument("--json", dest="json_out")
    a = ap.parse_args()
    from archive.fill import FillSpec, resolve_method
    from archive.formats import sha256_file
    from lacuna.modelfile import load_arrays

    meta, _ = load_arrays(a.model)
    spec = FillSpec(resolve_method(a.method, meta), a.model, sha256_file(a.model), meta["method"], "gaps", 0)
    configs = a.configs.split(",")
    runs = []
    with tempfile.TemporaryDirectory(prefix="archive-bench-") as tmp:
        work = Path(tmp)
        paths = _links(batch_takes(a.takes), work / "links")
        print(f"batch: {len(paths)} takes, method {spec.method}, model {a.model}", file=sys.stderr)
        for r in range(a.rounds):
            order = configs[r % len(configs):] + configs[: r % len(configs)]
            for kind in order:
                res = run_one(kind, paths, spec, a.model, work)
                res["round"] = r
                runs.append(res)
                ts = res["task_stream"]
                print(f"round {r} {kind:>10}: {res['takes_per_s']:.3f} takes/s {res['frames_per_s']:.0f} frames/s "
                      f"wall {res['wall_s']:.1f} s, up {res['cluster_start_s']:.1f} s (with it {res['e2e_takes_per_s']:.3f} "
                      f"takes/s), ship {res['model_ship_s'] * 1e3:.1f} ms, tail {ts.get('tail_s') or 0:.2f} s, "
                      f"fill/take {res['work_s']['fill'] / res['takes']:.3f} s, gap/take {ts.get('gap_s_mean') or 0:.4f} s, "
                      f"client CPU {res['client_cpu_s']:.1f} s, "
                      f"worker CPU {res['worker_cpu_s']:.1f} s ({res['cpu_share']:.2f} of each worker's wall), "
                      f"load {res['load1_before']:.1f}->{res['load1_after']:.1f}", file=sys.stderr, flush=True)
    summ = {}
    for kind in configs:
        rs = [x for x in runs if x["config"] == kind]
        summ[kind] = {"takes_per_s_median": float(np.median([x["takes_per_s"] for x in rs])),
                      "e2e_takes_per_s_median": float(np.median([x["e2e_takes_per_s"] for x in rs])),
                      "frames_per_s_median": float(np.median([x["frames_per_s"] for x in rs]))}
    for a1, a2 in (("local-1", "local-2"), ("loopback-1", "loopback-2"), ("local-1-cold", "local-2-cold")):
        if a1 in summ and a2 in summ:
            pairs = list(zip([x for x in runs if x["config"] == a1], [y for y in runs if y["config"] == a2]))
            summ[f"speedup_{a2}_over_{a1}_per_round"] = [round(y["takes_per_s"] / x["takes_per_s"], 3) for x, y in pairs]
            summ[f"e2e_speedup_{a2}_over_{a1}_per_round"] = [round(y["e2e_takes_per_s"] / x["e2e_takes_per_s"], 3)
                                                           for x, y in pairs]
            summ[f"load1_{a1}_{a2}_per_round"] = [[x["load1_before"], y["load1_after"]] for x, y in pairs]
    out = {"takes": a.takes, "method": spec.method, "model": a.model, "drop": "gaps", "runs": runs, "summary": summ,
           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "cpus": os.cpu_count()}
    print(json.dumps(summ, indent=1))
    if a.json_out:
        Path(a.json_out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json_out).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
