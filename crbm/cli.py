"""``lacuna train crbm`` and ``lacuna generate crbm``."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from crbm.released import RELEASED, RELEASED_INPUT
from lacuna.errors import LacunaError


def add_commands(cli) -> None:
    p = cli.train("crbm", help="train a conditional RBM filler (Taylor, Hinton & Roweis 2006)")
    p.add_argument("data", nargs="*", metavar="DATA", help="motion files to train on (.amc, .bvh, .csv; resampled to --fps)")
    p.add_argument("--protocol", help="train on a protocol's training set instead (e.g. taylor2007)")
    p.add_argument("--asf", help="ASF skeleton when it is not beside the AMC files")
    p.add_argument("-o", "--output", required=True, help="model file to write (.npz)")
    p.add_argument("--hidden", type=int, default=150, help="binary hidden units (default 150)")
    p.add_argument("--order", type=int, default=3, help="past frames feeding the directed connections (default 3)")
    p.add_argument("--epochs", type=int, default=None, help="CD-1 epochs (default: 2000 on ~2600 frames, "
                   "scaled down on bigger sets to ~52k mini-batch updates)")
    p.add_argument("--fps", type=float, default=30.0, help="train at this frame rate (default 30, as the paper)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--history-noise", type=float, default=RELEASED["history_noise"],
                   help="std of noise on the conditioning history (default 1, the released code; 0 = none)")
    p.add_argument("--positive-hidden", choices=["sample", "prob"], default=RELEASED["positive_hidden"],
                   help="hidden states in the data term: probabilities (default, the released code) or "
                   "sampled (the paper's text)")
    p.add_argument("--bias-init-std", type=float, default=RELEASED["bias_init_std"],
                   help="biases start from N(0, this^2) (default 0.01, the released code; 0 = zeros)")
    p.add_argument("--batches", choices=["fixed", "reshuffle"], default=RELEASED["batches"],
                   help="mini-batches cut once (default, the released code) or reshuffled every epoch")
    p.add_argument("--root-mode", choices=["raw", "relative"], default=RELEASED_INPUT["root_mode"],
                   help="root channels as captured (default, the released code's input) or body-centred "
                   "(heading-relative, the paper's section 4; the improved variants' choice)")
    p.add_argument("--average-last", type=float, default=0.0,
                   help="return the parameters averaged over this final fraction of epochs (0 = the paper)")
    p.add_argument("--levels", type=int, choices=[1, 2], default=1, help="2 adds the section-6 second level")
    p.add_argument("--members", type=int, default=1,
                   help="train this many CRBMs from seeds seed, seed+1000, ... and fill with all of them "
                   "pooled (crbm-ens uses 3; default 1)")
    p.add_argument("--gibbs", type=int, default=30, help="fill: Gibbs iterations per frame (default 30)")
    p.add_argument("--chains", type=int, default=1, help="fill: parallel chains averaged (default 1)")
    p.add_argument("--mode", choices=["gibbs", "mean-field"], default="gibbs")
    p.add_argument("--bias-rate", type=float, default=0.0,
                   help="fill: per-stream bias adaptation rate per frame (0 = the paper; crbm-imp uses 0.02)")
    p.add_argument("--scheduler", metavar="ADDR", help="train the --members on this Dask cluster (tcp://HOST:PORT), one per task")
    p.add_argument("--workers", type=int, metavar="N", help="the same on a local Dask cluster of N worker processes")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress on stderr")
    from mocap import skelmap

    skelmap.add_argument(p)
    p.set_defaults(func=_run_train)

    g = cli.generate("crbm", help="generate motion from a trained CRBM, seeded with real frames")
    g.add_argument("model", help="CRBM model file (.npz)")
    g.add_argument("--seed-frames", required=True, metavar="FILE", help="motion file (.amc, .bvh) whose frames seed the model")
    g.add_argument("--start", type=int, default=0, help="first seed frame (at the model's frame rate)")
    g.add_argument("--seed-length", type=int, default=None, help="seed frames (default order + 1)")
    g.add_argument("--frames", type=int, required=True, help="frames to generate (at the model's frame rate)")
    g.add_argument("--asf", help="ASF skeleton when it is not beside the seed AMC")
    g.add_argument("--seed", type=int, default=0, help="sampler seed")
    g.add_argument("--out-fps", type=float, default=None, help="resample the output (default: the seed file's rate)")
    g.add_argument("-o", "--output", required=True, help="motion file to write (.amc, .bvh, .csv: as the seed's skeleton allows)")
    g.set_defaults(func=_run_generate)


def _read_amc(path: str, asf: str | None, quiet: bool = False):
    """Any motion file (the name is kept for callers): AMC with its ASF, BVH, CSV; a leading
    T-pose (CMU's BVH) skipped."""
    from mocap.io import read_motion
    from mocap.tpose import skip_tpose

    if not Path(path).exists():
        raise LacunaError(f"{path}: no such file")
    return skip_tpose(read_motion(path, asf=asf), quiet)


def _run_train(args: argparse.Namespace) -> int:
    from crbm.train import train_model
    from mocap.representation import resample

    if bool(args.data) == bool(args.protocol):
        raise LacunaError("give either AMC files or --protocol (got " + ("both" if args.data else "neither") + ")")
    if args.protocol:
        from mocap.protocols import get_protocol

        ts = get_protocol(args.protocol).training_set()
        seqs, channels, names, fps = ts.sequences, ts.channels, ts.names, ts.fps
    else:
        from mocap import skelmap

        ms = [_read_amc(p, args.asf, args.quiet) for p in args.data]
        channels = ms[0].channels
        if args.root_mode == "relative":
            skelmap.Binding.of(channels, args.skeleton, args.data[0])  # relative root: the map must fit
        for m in ms[1:]:
            if m.channels != channels:
                raise LacunaError(f"{m.source}: channels differ from {ms[0].source}")
        seqs = [resample(m.frames, m.fps, args.fps, channels) for m in ms]
        names, fps = [Path(p).stem for p in args.data], args.fps
    if not args.quiet:
        print(f"training crbm on {len(seqs)} sequences, {sum(len(s) for s in seqs)} frames at {fps:g} Hz",
              file=sys.stderr)
    from archive.dist_cli import training_cluster  # a no-op without --scheduler/--workers

    with training_cluster(args, "crbm"):
        model = train_model(seqs, channels, hidden=args.hidden, order=args.order, epochs=args.epochs, seed=args.seed,
                            history_noise=args.history_noise, positive_hidden=args.positive_hidden,
                            bias_init_std=args.bias_init_std, batches=args.batches,
                            average_last=args.average_last, levels=args.levels, members=args.members,
                            n_gibbs=args.gibbs, n_chains=args.chains, mode=args.mode, bias_rate=args.bias_rate,
                            names=names, fps=fps, skeleton=args.skeleton, root_mode=args.root_mode,
                            # the raw root is the released code's input: angles as captured too
                            unwrap=args.root_mode != RELEASED_INPUT["root_mode"], progress=not args.quiet)
    if not args.protocol:
        from mocap.fk import skeleton_record

        rec = skeleton_record(ms[0])  # for FK wherever the model goes (mocap.fk.from_record)
        if rec:
            model.meta.setdefault("training", {})["skeleton"] = rec
    model.save(args.output)
    tr = model.meta["training"]
    print(f"wrote {args.output}: {tr['epochs']} epochs in {tr['seconds']:.1f} s, "
          f"reconstruction error {tr['reconstruction_error']:.3f} per frame")
    return 0


def _run_generate(args: argparse.Namespace) -> int:
    from crbm.generate import generate
    from crbm.persist import load
    from mocap.io import write_motion
    from mocap.motion import Motion
    from mocap.representation import resample

    model = load(args.model)
    fps = model.meta.get("training", {}).get("fps") or 30.0
    m = _read_amc(args.seed_frames, args.asf)
    missing = [c for c in model.channels if c not in m.channels]
    if missing:
        raise LacunaError(f"{args.seed_frames}: lacks the model's channels, e.g. {missing[:3]}")
    frames = resample(m.frames[:, m.index(model.channels)], m.fps, fps, model.channels)
    n_seed = args.seed_length or model.crbm.order + 1
    if args.start < 0 or args.start + n_seed > frames.shape[0]:
        raise LacunaError(f"{args.seed_frames}: has {frames.shape[0]} frames at {fps:g} Hz; "
                          f"cannot take {n_seed} seed frames from frame {args.start}")
    out = generate(model, frames[args.start : args.start + n_seed], args.frames, seed=args.seed)
    out_fps = args.out_fps or m.fps
    full = np.tile(m.frames[args.start * int(round(m.fps / fps)) if m.fps >= fps else 0], (out.shape[0], 1))
    full[:, m.index(model.channels)] = out
    if abs(out_fps - fps) > 1e-9:
        full = resample(full, fps, out_fps, m.channels)
    write_motion(args.output, Motion(full, list(m.channels), out_fps, m.skeleton, args.output))
    print(f"wrote {args.output}: {n_seed} seed + {args.frames} generated frames at {fps:g} Hz, "
          f"written at {out_fps:g} Hz")
    return 0
