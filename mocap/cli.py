"""`lacuna eval`: score a method on a fill protocol."""
from __future__ import annotations

import argparse
import json

from lacuna import registry


def add_commands(cli) -> None:
    p = cli.command("eval", help="score a fill method on a protocol (pan2009, taylor2007, gaps)")
    p.add_argument("--protocol", required=True, choices=["pan2009", "taylor2007", "gaps"])
    p.add_argument("--method", required=True, help="hold, nn, scaled-nn, interp, hlm, crbm, ... (see `lacuna methods`)")
    p.add_argument("--model", help="score this trained model file instead of training with defaults")
    p.add_argument("--test", action="append", metavar="FILE",
                   help="score this recording (AMC; BVH/CSV where supported) with the protocol's erasure; "
                        "repeat for several (one trained model scores every file)")
    p.add_argument("--asf", help="ASF skeleton for --test when it is not beside the AMC")
    p.add_argument("--split", choices=["validation", "test"],
                   help="gaps: the takes scored (default validation; test figures are labelled test); "
                        "pan2009: that split's walks, trained without any validation or test take")
    p.add_argument("--train-split", action="store_true",
                   help="pan2009: train on the paper's set minus every validation and test take (for --test)")
    p.add_argument("--json", dest="json_out", metavar="OUT", help="write every figure as JSON")
    p.add_argument("--plot", metavar="OUT.png", help="plot truth, fill and its 2-std band for a few erased channels")
    p.add_argument("--fills", metavar="DIR", help="write DIR/<take>[-<pattern>][-seed<k>].npz per case: "
                                                   "truth, fill, std, erased, channels, fps")
    p.add_argument("--seed", type=int, action="append", help="occlusion seed of the gaps protocol (repeatable; default 0)")
    p.add_argument("--seeds", metavar="A-B|A,B,...", help="gaps: several occlusion seeds, e.g. 0-4; figures pool them")
    p.add_argument("--option", "-O", action="append", default=[], metavar="KEY=VALUE",
                   help="training option passed to the method (JSON value), e.g. -O styles=4")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress on stderr")
    p.add_argument("--train", action="append", metavar="FILE", dest="train_files",
                   help="train the method on this take (repeatable) instead of the protocol's training set: "
                   "takes of another skeleton (BVH) for --test files of that skeleton")
    from mocap import skelmap

    skelmap.add_argument(p)
    p.set_defaults(func=_run_eval)

    lm = cli.command("methods", help="list the fill methods lacuna knows")
    lm.set_defaults(func=_run_methods)


def _parse_options(items: list[str]) -> dict:
    out = {}
    for it in items:
        if "=" not in it:
            raise ValueError(f"--option expects KEY=VALUE (got {it!r})")
        k, v = it.split("=", 1)
        try:
            out[k.strip()] = json.loads(v)
        except json.JSONDecodeError:
            out[k.strip()] = v
    return out


def parse_seeds(text: str | None, repeated: list[int] | None) -> list[int]:
    """``0-4`` -> [0..4], ``1,3`` -> [1, 3]; with repeated ``--seed`` values added; default [0]."""
    out = list(repeated or [])
    for part in (text or "").split(","):
        part = part.strip()
        if not part:
            continue
        lo, sep, hi = part.partition("-")
        try:
            out += list(range(int(lo), int(hi) + 1)) if sep else [int(lo)]
        except ValueError:
            raise ValueError(f"--seeds expects A-B or A,B,... (got {text!r})") from None
    if text and not out:
        raise ValueError(f"--seeds expects A-B or A,B,... (got {text!r})")
    return list(dict.fromkeys(out)) or [0]


def _run_eval(args: argparse.Namespace) -> int:
    from mocap import evaluate as ev

    seeds = parse_seeds(args.seeds, args.seed)
    res = ev.evaluate(args.protocol, args.method, args.model, args.test, args.asf,
                      _parse_options(args.option), progress=not args.quiet, seeds=seeds,
                      split=args.split, train_split=args.train_split, fills_dir=args.fills,
                      skeleton=args.skeleton, train_files=args.train_files)
    print(ev.format_table(res))
    if args.fills:
        print(f"fills: {args.fills}")
    if args.json_out:
        ev.write_json(res, args.json_out)
        print(f"results: {args.json_out}")
    if args.plot:
        ev.plot(res, args.plot)
        print(f"plot: {args.plot}")
    return 0


def _run_methods(args: argparse.Namespace) -> int:
    for name in registry.methods():
        spec = registry.get_method(name)
        print(f"{name:<22} {'causal ' if spec.causal else 'offline'}  {spec.description}")
    return 0
