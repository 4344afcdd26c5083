"""``lacuna data``: where the motion data is, what it holds, and fetching CMU's files.

    lacuna data where
    lacuna data list [--dir DIR]
    lacuna data fetch cmu --subjects 07 35 [--trials 07_01 ...] [--base-url URL] [--dest DIR]
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from lacuna.errors import DataError
from mocap import datasets
from mocap.fetch import CMU_BASE_URL, CMU_TRIALS, TIMEOUT_S, fetch_cmu


def _source(d: Path) -> str:
    if os.environ.get("LACUNA_DATA"):
        return "from $LACUNA_DATA"
    if d.resolve() == datasets.cache_dir().resolve():
        return "the per-user cache, filled by `lacuna data fetch`"
    return "the shared data beside this checkout"


def run_where(args: argparse.Namespace) -> int:
    d = datasets.data_dir()
    if d is None:
        print(
            "lacuna: no motion data: set LACUNA_DATA, work beside ../shared/data, or run "
            f"`lacuna data fetch cmu --subjects 07 35` (downloads into {datasets.cache_dir()})",
            file=sys.stderr,
        )
        return 1
    print(d)
    print(f"({_source(d)})", file=sys.stderr)
    return 0


def run_list(args: argparse.Namespace) -> int:
    d = Path(args.dir) if args.dir else datasets.data_dir(required=True)
    cmu = d / "cmu"
    if not cmu.is_dir():
        raise DataError(f"{d} has no cmu/ directory (expected cmu/<SS>/<SS>.asf and <SS>_<TT>.amc)")
    print(f"{d}:")
    for sd in sorted(p for p in cmu.iterdir() if p.is_dir()):
        s = sd.name
        trials = sorted(p.stem for p in sd.glob("*.amc"))
        asf = "asf" if (sd / f"{s}.asf").exists() else "NO ASF"
        line = f"  cmu/{s}  {asf}  {len(trials)} trials: {' '.join(trials)}"
        missing = [t for t in CMU_TRIALS.get(s, []) if t not in trials]
        if missing:
            line += f"  (not here: {' '.join(missing)})"
        print(line)
    return 0


def run_fetch(args: argparse.Namespace) -> int:
    if not args.subjects and not args.trials:
        raise ValueError("name subjects (--subjects 07 35) or trials (--trials 07_01)")
    dest = Path(args.dest) if args.dest else datasets.cache_dir()
    fetch_cmu(args.subjects or [], args.trials, args.base_url, dest, args.timeout)
    used = datasets.data_dir()
    if used is None or used.resolve() != dest.resolve():
        print(f"note: lacuna reads data from {used or 'nowhere yet'}; set LACUNA_DATA={dest} to use these files", file=sys.stderr)
    return 0


def add_commands(cli) -> None:
    p = cli.command("data", help="the motion data directory: where, list, fetch")
    sub = p.add_subparsers(dest="data_what", metavar="ACTION")
    p.set_defaults(func=lambda a, p=p: (p.print_help(), 2)[1])

    w = sub.add_parser("where", help="print the data directory in use", description="Print the data directory in use "
                       "($LACUNA_DATA, else ../shared/data beside the checkout, else the per-user cache).")
    w.set_defaults(func=run_where)

    ls = sub.add_parser("list", help="list subjects and trials in the data directory")
    ls.add_argument("--dir", help="list this data directory instead of the one in use")
    ls.set_defaults(func=run_list)

    f = sub.add_parser("fetch", help="download public motion data", description="Download public motion data.")
    fsub = f.add_subparsers(dest="fetch_what", metavar="DATASET")
    f.set_defaults(func=lambda a, f=f: (f.print_help(), 2)[1])
    c = fsub.add_parser(
        "cmu",
        help="CMU Graphics Lab ASF/AMC files",
        description=(
            "Download ASF/AMC files of the CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu) "
            "into DEST/cmu/<SS>/. Files already there are skipped, so an interrupted fetch resumes. "
            "Every file is checked to parse before it is kept. Without --trials, each subject's "
            f"default trials are fetched ({'; '.join(f'{s}: {len(t)}' for s, t in CMU_TRIALS.items())})."
        ),
    )
    c.add_argument("--subjects", nargs="+", default=[], metavar="SS", help="subject numbers, e.g. 07 35")
    c.add_argument("--trials", nargs="+", metavar="SS_TT", help="only these trials, e.g. 07_01 07_02")
    c.add_argument("--base-url", default=CMU_BASE_URL, help=f"where subjects/<SS>/ live (default {CMU_BASE_URL})")
    c.add_argument("--dest", help=f"data directory to fill (default: the per-user cache, {datasets.cache_dir()})")
    c.add_argument("--timeout", type=float, default=TIMEOUT_S, help=f"seconds to wait on the server (default {TIMEOUT_S:g})")
    c.set_defaults(func=run_fetch)
