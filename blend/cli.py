"""`lacuna train default-blend`: fit the stacked blend (``default``'s first expert) on motion files
and write a model file (kind "default", as before the switch)."""
from __future__ import annotations

import argparse
import os
import sys


def add_commands(cli) -> None:
    p = cli.train("default-blend", help="train the stacked blend of hold, damped velocity and a regression on the "
                                        "observed channels (default's first expert) on motion files")
    add_data_arguments(p)
    p.add_argument("--calibrate", nargs="+", metavar="FILE", default=None,
                   help="held-out takes to fit the stacking weights and the std on (default: the weights shipped "
                        "in blend/weights.json, fitted on the validation split)")
    p.set_defaults(func=_run)


def add_data_arguments(p) -> None:
    """The arguments `lacuna train default` and `default-blend` share: the motion files, the model
    file, a rate to resample to, quiet, and the skeleton map."""
    from mocap import skelmap

    p.add_argument("data", nargs="+", metavar="DATA", help="motion files (.amc with its .asf beside it, .bvh, .csv)")
    p.add_argument("-o", "--output", required=True, help="model file to write (.npz)")
    p.add_argument("--fps", type=float, help="resample every file to this rate first")
    p.add_argument("--quiet", "-q", action="store_true")
    skelmap.add_argument(p)


def _load(paths: list[str], fps: float | None):
    from hlm.cli import _read
    from lacuna.errors import LacunaError
    from mocap.representation import resample

    motions = [_read(p) for p in paths]
    ch = motions[0].channels
    rate = fps or motions[0].fps
    seqs = []
    for p, m in zip(paths, motions):
        if m.channels != ch:
            raise LacunaError(f"{p}: channels differ from {paths[0]} ({len(m.channels)} vs {len(ch)}); "
                              "train on takes of one skeleton")
        if abs(m.fps - rate) > 1e-6:
            if not fps:
                raise LacunaError(f"{p}: {m.fps} fps differs from {motions[0].fps} fps; pass --fps to resample")
            seqs.append(resample(m.frames, m.fps, rate, ch))
        else:
            seqs.append(m.frames)
        if seqs[-1].shape[0] < 10:
            raise LacunaError(f"{p}: has {seqs[-1].shape[0]} frames; need at least 10")
    return seqs, ch, rate, motions[0]


def _run(args: argparse.Namespace) -> int:
    from blend.train import train_model

    seqs, ch, rate, first = _load(args.data, args.fps)
    cal = None
    if args.calibrate:
        cseqs, cch, _, _ = _load(args.calibrate, rate)
        if cch != ch:
            from lacuna.errors import LacunaError

            raise LacunaError(f"{args.calibrate[0]}: channels differ from the training takes'")
        from mocap import skelmap

        # the weights are fitted on dropouts of the joint groups: a skeleton without any would erase
        # nothing but the root (SkeletonError naming the skeleton and the bones looked for)
        skelmap.Binding.of(ch, args.skeleton, args.calibrate[0]).mask(list(skelmap.GROUPS), "--calibrate")
        cal = [(os.path.basename(p), s, "take") for p, s in zip(args.calibrate, cseqs)]
    model = train_model(seqs, ch, [os.path.basename(p) for p in args.data], calibrate=cal, fps=rate,
                        skeleton=args.skeleton)
    from mocap.fk import skeleton_record

    # as `lacuna train hlm|crbm` do: the rate (lacuna fill checks a take's against it) and the
    # skeleton (FK for lacuna view and positions in replies) go with the model
    training = model.meta.setdefault("training", {})
    training["fps"] = rate
    rec = skeleton_record(first)
    if rec:
        training["skeleton"] = rec
    model.save(args.output)
    from blend.groups import limb_channels

    skel = model.meta.get("skeleton_map") or ""
    if not limb_channels(model.group):
        # no channel in a body part: every missing channel would only be held
        why = (f"its bones match no known skeleton ({', '.join(_maps())}): pass --skeleton NAME|FILE"
               if not skel else f"no channel falls in a body part of skeleton {skel}")
        print(f"lacuna: warning: {args.data[0]}: {why}; default will hold the last value of every missing channel",
              file=sys.stderr)
    if not args.quiet:
        print(f"default-blend: {len(seqs)} takes ({skel or 'no known skeleton'}), {sum(s.shape[0] for s in seqs)} frames at {rate:g} fps, "
              f"{len(model.reg_idx)} regression channels, weights "
              f"{'fitted on ' + str(len(cal)) + ' takes' if cal else 'shipped (validation split)'}; wrote {args.output}",
              file=sys.stderr)
    return 0


def _maps() -> list[str]:
    from mocap import skelmap

    return skelmap.available()
