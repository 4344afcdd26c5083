"""`lacuna eval`: score a method on a fill protocol."""
from __future__ import annotations

import argparse
import json

from lacuna import registry


def add_commands(cli) -> None:
    p = cli.command("eval", help="score a fill method on a protocol (pan2009, taylor2007, gaps)")
    p.add_argument("--protocol", required=True, choices=["pan2009", "taylor2007", "gaps"])
    p.add_argument("--method", required=True, help="hold, nn, scaled-nn, interp, hlm, crbm, ... (see --list)")
    p.add_argument("--model", help="score this trained model file instead of training with defaults")
    p.add_argument("--test", help="score another recording (AMC; BVH/CSV where supported) with the protocol's erasure")
    p.add_argument("--asf", help="ASF skeleton for --test when it is not beside the AMC")
    p.add_argument("--json", dest="json_out", metavar="OUT", help="write results as JSON")
    p.add_argument("--plot", metavar="OUT.png", help="plot truth, fill and nearest-neighbour fill of erased channels")
    p.add_argument("--seed", type=int, default=0, help="seed of the gaps protocol's occlusion (default 0)")
    p.add_argument("--option", "-O", action="append", default=[], metavar="KEY=VALUE",
                   help="training option passed to the method (JSON value), e.g. -O styles=4")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress on stderr")
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


def _run_eval(args: argparse.Namespace) -> int:
    from mocap import evaluate as ev

    res = ev.evaluate(args.protocol, args.method, args.model, args.test, args.asf,
                      _parse_options(args.option), progress=not args.quiet, seed=args.seed)
    print(ev.format_table(res))
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
