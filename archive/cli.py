"""``lacuna fill TAKE... --out DIR``: fill whole recorded takes offline, on a Dask cluster."""
from __future__ import annotations

import argparse
import json
import os
import sys

from lacuna.errors import LacunaError


def add_commands(cli) -> None:
    p = cli.command("fill", help="fill recorded takes offline (dirs, globs, files; AMC/BVH/CSV/.lrec) on a Dask "
                                 "cluster, resumable; each output in its input's format plus a .fill.json sidecar")
    p.add_argument("takes", nargs="+", metavar="TAKE", help="take files, directories (searched recursively) or globs")
    p.add_argument("--out", required=True, metavar="DIR", help="directory for the filled takes (mirrors directory arguments)")
    p.add_argument("--model", metavar="FILE", help="trained model file (.npz); default method: its best offline one")
    p.add_argument("--method", metavar="M", help="method: one of the model's (e.g. hlm-offline), or hold|interp without --model")
    p.add_argument("--scheduler", metavar="ADDR", help="an existing Dask scheduler, tcp://HOST:PORT (default: a local cluster)")
    p.add_argument("--workers", type=int, metavar="N",
                   help="local cluster worker processes (default: one per CPU); 0 = in this process, no Dask")
    p.add_argument("--drop", metavar="PATTERN", help="rehearsal: erase values of complete takes by a replay pattern "
                   "(gaps, gaps:left-arm, pan2009, taylor2007:right-leg) and report the error against them")
    p.add_argument("--seed", type=int, default=0, help="seed of the --drop pattern (default 0)")
    p.add_argument("--json", dest="json_out", metavar="SUMMARY", help="write the batch summary (and every take's row) as JSON")
    p.add_argument("--force", action="store_true", help="fill every take again, even those already done")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from archive.batch import run_batch
    from archive.fill import FillSpec, resolve_method
    from archive.formats import sha256_file
    from archive.takes import discover

    meta = None
    sha = None
    if args.model:
        from lacuna.modelfile import load_arrays

        if not os.path.isfile(args.model):
            raise LacunaError(f"--model {args.model}: no such file")
        meta, _ = load_arrays(args.model)
        sha = sha256_file(args.model)
    method = resolve_method(args.method, meta)
    if args.drop:
        from clients.takes import check_pattern

        check_pattern(args.drop)  # an unknown pattern fails before any take is read
    jobs = discover(args.takes, args.out)
    os.makedirs(args.out, exist_ok=True)
    spec = FillSpec(method, args.model, sha, meta.get("method") if meta else None, args.drop, args.seed)
    if args.force:
        from archive.formats import FILL_SUFFIX

        for j in jobs:
            if os.path.exists(j.output + FILL_SUFFIX):
                os.unlink(j.output + FILL_SUFFIX)
    if not args.quiet:
        print(f"fill: {len(jobs)} takes, method {method}" + (f", model {args.model}" if args.model else "")
              + (f", drop {args.drop}" if args.drop else ""), file=sys.stderr, flush=True)
    from archive.batch import pending

    up = None

    if not pending(jobs, spec, args.model)[0]:
        res = run_batch(jobs, spec, args.model, None, progress=False)   # every take is done: no cluster needed
    elif args.workers == 0:
        if args.scheduler:
            raise LacunaError("--workers 0 fills in this process; it cannot be combined with --scheduler")
        res = run_batch(jobs, spec, args.model, None, progress=not args.quiet)
    else:
        import time

        from archive.cluster import open_client

        t0 = time.perf_counter()
        with open_client(args.scheduler, args.workers) as client:
            up = time.perf_counter() - t0
            res = run_batch(jobs, spec, args.model, client, progress=not args.quiet)
    summ = {"method": method, "model": args.model, "model_sha256": sha, "drop": args.drop, "out": args.out,
            **res.summary()}
    if up is not None:  # the cluster's start (or connection), apart from the batch's wall time
        summ["cluster_start_s"] = round(up, 3)
    _print_table(summ, res.rows)
    if args.json_out:
        from mocap.atomic import atomic_write_text

        atomic_write_text(args.json_out, json.dumps({"summary": summ, "takes": res.rows}, indent=2, sort_keys=True) + "\n")
        print(f"json: {args.json_out}")
    return 1 if res.failed else 0


def _print_table(s: dict, rows: list[dict]) -> None:
    where = f"{s['workers']} workers at {s['scheduler']}" if s["scheduler"] else "this process"
    print(f"{'takes':>8} {'filled':>7} {'skipped':>8} {'failed':>7} {'frames':>9} {'values filled':>14} "
          f"{'wall s':>8} {'takes/s':>8} {'frames/s':>9}")
    tps = "-" if s["takes_per_s"] is None else f"{s['takes_per_s']:.2f}"
    fps = "-" if s["frames_per_s"] is None else f"{s['frames_per_s']:.0f}"
    print(f"{s['takes']:>8} {s['filled']:>7} {s['skipped']:>8} {s['failed']:>7} {s['frames']:>9} "
          f"{s['values_filled']:>14} {s['wall_s']:>8.2f} {tps:>8} {fps:>9}")
    if s["filled"] + s["failed"]:
        print(f"method {s['method']} on {where}; outputs in {s['out']}")
    else:
        print(f"nothing to do: every take is already filled with {s['method']} in {s['out']} (--force fills again)")
    reh = [r["rehearsal"]["rms_deg"] for r in rows if r.get("rehearsal") and r["rehearsal"]["rms_deg"] is not None]
    if reh:
        import numpy as np

        print(f"rehearsal ({s['drop']}): RMS error on erased angles, mean over {len(reh)} takes {np.mean(reh):.2f} deg")
    for f in s["failures"]:
        print(f"FAILED {f['source']}: {f['error']}")
