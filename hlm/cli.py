"""`lacuna train hlm`: fit an HLM on motion files and write a model file."""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from lacuna.errors import LacunaError


def add_commands(cli) -> None:
    p = cli.train("hlm", help="train a Hierarchical Locomotion Model (Pan & Torresani 2009) on locomotion takes")
    p.add_argument("data", nargs="+", metavar="DATA", help="motion files (.amc with its .asf beside it, .bvh, .csv)")
    p.add_argument("-o", "--output", required=True, help="model file to write (.npz)")
    p.add_argument("--styles", "-C", type=int, default=4, help="number of styles C (default 4)")
    p.add_argument("--cycle-frames", "-N", type=int, default=140,
                   help="expected cycle length N in frames at the data rate; M = 2 N latent states (default 140)")
    p.add_argument("--states", type=int, help="latent cycle states M (default 2 N, the paper's choice)")
    p.add_argument("--jumps", type=int, default=3, help="maximum phase advance J per frame (default 3)")
    p.add_argument("--iterations", type=int, default=15, help="EM iterations (default 15)")
    p.add_argument("--sweeps", type=int, default=3, help="variational updates per E-step (default 3)")
    p.add_argument("--restarts", type=int, default=3, help="seeded restarts; the best bound is kept (default 3)")
    p.add_argument("--seed", type=int, default=0, help="first restart's seed (default 0)")
    p.add_argument("--root-mode", choices=["raw", "relative", "auto"], default=None,
                   help="root as raw angles/positions (the paper) or heading-relative motion; auto (the default): "
                        "relative where the skeleton has root.tx..rz")
    p.add_argument("--root-tau", type=float, default=None, metavar="FRAMES",
                   help="relative root: the fixed part of the damping of the root's motion over a root dropout, "
                        "1/FRAMES per frame (with --root-turn > 0: the heading's alone); 0 = none "
                        "(see docs/BENCHMARKS.md, HLM root representation)")
    p.add_argument("--root-turn", type=float, default=None, metavar="B",
                   help="relative root: the damping's rate grows by B x the yaw rate (rad/frame) seen before the "
                        "dropout: a straight walker keeps walking, a turning one is held (default 8; 0 = off)")
    p.add_argument("--normalize", action=argparse.BooleanOptionalAction, default=False,
                   help="scale features to unit variance before training (default off, as the paper)")
    p.add_argument("--fps", type=float, help="resample every file to this rate first")
    p.add_argument("--kappa", type=float, default=3.0,
                   help="stream-cycle adaptation pseudo-count per knot at inference (0 = the paper's filler; default 3)")
    p.add_argument("--kappa-global", type=float, default=3.0,
                   help="pseudo-count of the stream's constant offset (0 = knots only; default 3)")
    p.add_argument("--width", type=int, default=8,
                   help="stream-cycle knots are 2 width + 1 latent states apart (default 8)")
    p.add_argument("--style-switch", type=float, default=0.0, metavar="P",
                   help="probability per frame that the performer changes style, e.g. 1e-3 for takes that go "
                        "from walking to running (default 0: the paper's one style per take, better on single-style "
                        "takes; see docs/BENCHMARKS.md)")
    p.add_argument("--cond-shrink", type=float, default=None, metavar="S",
                   help="the fill's correction from the observed features' residuals (hlm.condfill), 0..1 "
                        "(default 0.5, chosen on VALIDATION; 0: the paper's eq. 18 fill, no covariance fitted)")
    p.add_argument("--lag", type=int, default=15, help="frames of look-ahead of the fixed-lag filler (default 15)")
    p.add_argument("--scheduler", metavar="ADDR", help="run each E-step over the takes on this Dask cluster "
                   "(tcp://HOST:PORT; archive/hlm_dist.py): the same bound and parameters as one process")
    p.add_argument("--workers", type=int, metavar="N", help="the same on a local Dask cluster of N worker processes")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress lines on stderr")
    from mocap import skelmap

    skelmap.add_argument(p)
    p.set_defaults(func=_run_train)


def _read(path: str, quiet: bool = False):
    if not os.path.exists(path):
        raise LacunaError(f"{path}: no such file")
    from mocap.io import read_motion
    from mocap.tpose import skip_tpose

    return skip_tpose(read_motion(path), quiet)


def _run_train(args: argparse.Namespace) -> int:
    from hlm.methods import train_model
    from mocap.representation import resample

    if args.cond_shrink is not None and not 0.0 <= args.cond_shrink <= 1.0:
        raise LacunaError(f"--cond-shrink must be in [0, 1] (got {args.cond_shrink})")
    motions = [_read(p, args.quiet) for p in args.data]
    ch = motions[0].channels
    if args.skeleton or args.root_mode == "relative":
        from mocap import skelmap

        skelmap.Binding.of(ch, args.skeleton, args.data[0])  # an unknown map or bones: a clear error now
    for p, m in zip(args.data[1:], motions[1:]):
        if m.channels != ch:
            raise LacunaError(f"{p}: channels differ from {args.data[0]} ({len(m.channels)} vs {len(ch)}); "
                              "train on takes of one skeleton")
    fps = args.fps or motions[0].fps
    seqs = []
    for p, m in zip(args.data, motions):
        if abs(m.fps - fps) > 1e-6:
            if not args.fps:
                raise LacunaError(f"{p}: {m.fps} fps differs from {motions[0].fps} fps; pass --fps to resample")
            seqs.append(resample(m.frames, m.fps, fps, ch))
        else:
            seqs.append(m.frames)
        if seqs[-1].shape[0] < 2:
            raise LacunaError(f"{p}: has {seqs[-1].shape[0]} frames; need at least 2")
    if not args.quiet:
        n = sum(s.shape[0] for s in seqs)
        print(f"hlm: {len(seqs)} takes, {n} frames at {fps:g} fps, C={args.styles}, N={args.cycle_frames}, "
              f"M={args.states or 2 * args.cycle_frames}", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    from archive.dist_cli import training_cluster  # a no-op without --scheduler/--workers

    with training_cluster(args, "hlm"):
        model = train_model(seqs, ch, [os.path.basename(p) for p in args.data], progress=not args.quiet,
                            styles=args.styles, cycle_frames=args.cycle_frames, n_states=args.states, jumps=args.jumps,
                            n_iter=args.iterations, n_var=args.sweeps, restarts=args.restarts, seed=args.seed,
                            root_mode=args.root_mode, root_tau=args.root_tau, root_turn=args.root_turn,
                            normalize=args.normalize, kappa=args.kappa,
                            width=args.width, kappa_global=args.kappa_global, style_switch=args.style_switch,
                            lag=args.lag, skeleton=args.skeleton, cond_shrink=args.cond_shrink)
    model.meta["training"]["fps"] = fps
    from mocap.fk import skeleton_record

    rec = skeleton_record(motions[0])  # for FK wherever the model goes (mocap.fk.from_record)
    if rec:
        model.meta["training"]["skeleton"] = rec
    model.save(args.output)
    psi = np.array(model.meta["training"]["psi"])
    print(f"hlm: trained in {time.perf_counter() - t0:.1f} s, bound {model.meta['training']['bounds'][-1]:.8g}; "
          f"styles of the takes: {psi.argmax(1).tolist()}; wrote {args.output}")
    return 0
