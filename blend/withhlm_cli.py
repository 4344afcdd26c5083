"""`lacuna train default` (and its earlier name ``default-hlm``): train the stacked blend and the HLM
on motion files, write one model file (kind "default-hlm")."""
from __future__ import annotations

import argparse
import os
import sys


def add_commands(cli) -> None:
    for name, say in (("default", "train the recommended causal filler: the stacked blend (default-blend) on every "
                                  "file and the HLM on the locomotion ones, mixed online (blend.withhlm)"),
                      ("default-hlm", "the same as `lacuna train default` (its name before it became default)")):
        _add(cli.train(name, help=say))


def _add(p) -> None:
    from blend.cli import add_data_arguments

    add_data_arguments(p)
    p.add_argument("--hlm-data", nargs="+", metavar="FILE", default=None,
                   help="the locomotion files of DATA to train the HLM on (default: those the project's split "
                        "names walk, turn or run; every file where it names none)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from blend.cli import _load
    from blend.withhlm import LOCOMOTION, train_model
    from lacuna.errors import LacunaError
    from mocap import splits
    from mocap.fk import skeleton_record
    from mocap.protocols import TrainingSet

    seqs, ch, rate, first = _load(args.data, args.fps)
    stems = [os.path.splitext(os.path.basename(p))[0] for p in args.data]
    if args.hlm_data:
        given = {os.path.abspath(p) for p in args.hlm_data}
        unknown = given - {os.path.abspath(p) for p in args.data}
        if unknown:
            raise LacunaError(f"{sorted(unknown)[0]}: --hlm-data files must be among DATA")
        labels = ["walk" if os.path.abspath(p) in given else "other" for p in args.data]
    else:
        known = [splits.ACTIVITY.get(s) for s in stems]
        labels = [a or "walk" for a in known] if all(a is None for a in known) else [a or "other" for a in known]
    if not any(lab in LOCOMOTION for lab in labels):
        raise LacunaError("no locomotion file among DATA to train the HLM on (name them with --hlm-data)")
    ts = TrainingSet(seqs, list(ch), rate, [os.path.basename(p) for p in args.data], labels)
    model = train_model(ts, fps=rate, skeleton=args.skeleton)
    training = model.meta.setdefault("training", {})
    training["fps"] = rate
    rec = skeleton_record(first)
    if rec:
        training["skeleton"] = rec
    model.save(args.output)
    from blend.cli import _maps
    from blend.groups import limb_channels

    skel = model.default.meta.get("skeleton_map") or ""
    if not limb_channels(model.default.group):
        # as `lacuna train default-blend` warns: no channel in a body part, every missing one only held
        why = (f"its bones match no known skeleton ({', '.join(_maps())}): pass --skeleton NAME|FILE"
               if not skel else f"no channel falls in a body part of skeleton {skel}")
        print(f"lacuna: warning: {args.data[0]}: {why}; default's blend will hold the last value of every "
              "missing channel", file=sys.stderr)
    if not args.quiet:
        n = sum(lab in LOCOMOTION for lab in labels)
        print(f"default: the stacked blend on {len(seqs)} files ({skel or 'no known skeleton'}), the HLM on {n} "
              "locomotion files, "
              f"{sum(s.shape[0] for s in seqs)} frames at {rate:g} fps; wrote {args.output}", file=sys.stderr)
    return 0
