"""Choose the HLM's settings on the VALIDATION takes (``mocap.splits``), or score them once on TEST.

Trains the HLM on the TRAIN split's locomotion takes (walks, turns, runs; ``--train all`` adds
the non-locomotion ones) for each training setting, then fills every take of the chosen split,
for each inference setting, in three kinds of case:

  gaps       the ``gaps`` protocol's seeded bursts on joint groups, seeds 0..S-1 (since the
             ``eval`` branch's protocol these include bursts of the root group as well)
  gaps+root  the same, plus seeded bursts of the whole root (6 channels) on their own stream
  legs-only  pan2009's pattern: over the second half every channel but the 14 leg channels
             (root included) is erased

and reports, per activity (walk, turn, run, nonloco) and case, RMS degrees over the erased body
angles (all bursts, and bursts >= 0.5 s), and where the root is erased its translation error in
cm (RMS of the 3-D distance; CMU ASF length unit = 1/0.45 in = 5.644 cm), its heading (yaw) RMS
error in degrees, and the root's jump at the first erased frame (median cm).  Hold-last-value is
scored on the same cases.

    .venv/bin/python bench/hlm_validation.py --split validation --seeds 3 \
        --setting "raw:root_mode=raw" --setting "rel:root_mode=relative" --json out.json

A setting is ``label:key=value,key=value`` over ``hlm.methods.DEFAULTS`` (training and
inference keys alike); models are cached by their training keys in ``--cache``.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import hashlib
import json
import sys
import time
import zlib
from collections import defaultdict
from pathlib import Path

import numpy as np

from mocap import splits
from mocap.protocols import GAP_BINS, LEG_BONES, Gaps, bone
from mocap.representation import ROOT_POS, is_angle, wrap180

CM_PER_UNIT = 2.54 / 0.45
INFER_KEYS = ("kappa", "width", "kappa_global", "style_switch", "adapt_rate", "root_tau", "root_power", "cond_shrink",
               "root_turn", "root_turn_frames", "root_std")
LOCO = ("walk", "turn", "run")


def parse_setting(s: str) -> tuple[str, dict]:
    label, _, rest = s.partition(":")
    opts = {}
    for kv in filter(None, rest.split(",")):
        k, v = kv.split("=")
        try:
            opts[k] = int(v) if v.lstrip("-").isdigit() else float(v)
        except ValueError:
            opts[k] = v
    return label, opts


def root_bursts(take: str, T: int, seed: int, fps: float) -> list[tuple[int, int]]:
    rng = np.random.default_rng([seed, zlib.crc32((take + "/root").encode())])
    out, lo, hi = [], GAP_BINS[0][0], GAP_BINS[-1][1]
    t = fps * (Gaps.CLEAN_LEAD + rng.exponential(1.0 / Gaps.RATE_PER_GROUP))
    while t < T:
        a, b = int(t), min(T, int(t + np.exp(rng.uniform(np.log(lo), np.log(hi))) * fps))
        if b > a:
            out.append((a, b))
        t = b + fps * rng.exponential(1.0 / Gaps.RATE_PER_GROUP)
    return out


def make_cases(takes: list[str], seeds: int) -> list[dict]:
    cases = []
    for take in takes:
        m = splits.load_take(take)
        T, ch = m.frames.shape[0], m.channels
        root = np.array([c.startswith("root.") for c in ch])
        for s in range(seeds):
            obs, bursts = Gaps(seed=s).occlusion(take, T, ch, m.fps)
            cases.append(dict(take=take, kind="gaps", seed=s, truth=m.frames, obs=obs, bursts=bursts, roots=[],
                              channels=ch))
            obs2 = obs.copy()
            rb = root_bursts(take, T, s, m.fps)
            for a, b in rb:
                obs2[a:b, root] = False
            cases.append(dict(take=take, kind="gaps+root", seed=s, truth=m.frames, obs=obs2, bursts=bursts, roots=rb,
                              channels=ch))
        keep = np.array([bone(c) in LEG_BONES for c in ch])
        obs = np.ones((T, len(ch)), bool)
        obs[T // 2 :, ~keep] = False
        cases.append(dict(take=take, kind="legs-only", seed=0, truth=m.frames, obs=obs,
                          bursts=[("all", T // 2, T)], roots=[(T // 2, T)], channels=ch))
    return cases


def score(case: dict, fill: np.ndarray, acc: dict, key: tuple) -> list[float]:
    """Add the case's squared errors and counts to acc[key + (metric,)]; return the root's jumps (cm)."""
    ch, truth, obs = case["channels"], case["truth"], case["obs"]
    ang = np.array([is_angle(c) for c in ch])
    body = ang & np.array([not c.startswith("root.") for c in ch])
    err = fill - truth
    err[:, ang] = wrap180(err[:, ang])
    miss = ~obs & body[None]
    fps = 120.0
    long = np.zeros_like(miss)
    for _, a, b in case["bursts"]:
        if (b - a) / fps >= 0.5:
            long[a:b] = True
    for name, m in (("body", miss), ("body>=0.5s", miss & long)):
        acc[key + (name,)][0] += float((err[m] ** 2).sum())
        acc[key + (name,)][1] += int(m.sum())
    if case["roots"]:
        p = [ch.index(c) for c in ROOT_POS]
        d = np.linalg.norm(err[:, p], axis=1) * CM_PER_UNIT
        rm = np.zeros(truth.shape[0], bool)
        jumps = []
        for a, b in case["roots"]:
            rm[a:b] = True
            jumps.append(d[a])
        yaw = _yaw_err(fill, truth, ch)
        acc[key + ("root_cm",)][0] += float((d[rm] ** 2).sum())
        acc[key + ("root_cm",)][1] += int(rm.sum())
        acc[key + ("yaw_deg",)][0] += float((yaw[rm] ** 2).sum())
        acc[key + ("yaw_deg",)][1] += int(rm.sum())
        return jumps
    return []


def _yaw_err(fill: np.ndarray, truth: np.ndarray, ch: list[str]) -> np.ndarray:
    from mocap.representation import _matrix_to_ypr, _rxyz_to_matrix

    i = [ch.index(c) for c in ("root.rx", "root.ry", "root.rz")]

    def yaw(x):
        r = np.deg2rad(x[:, i])
        return np.rad2deg(_matrix_to_ypr(_rxyz_to_matrix(r[:, 0], r[:, 1], r[:, 2]))[0])

    return wrap180(yaw(fill) - yaw(truth))


def train(opts: dict, train_set: str, cache: Path):
    from hlm.methods import DEFAULTS, train_model
    from lacuna.modelfile import load_model

    tkeys = {k: v for k, v in {**DEFAULTS, **opts}.items() if k not in INFER_KEYS}
    h = hashlib.sha1(json.dumps([train_set, tkeys], sort_keys=True, default=str).encode()).hexdigest()[:12]
    path = cache / f"hlm-{h}.npz"
    if path.exists():
        return load_model(str(path)), tkeys
    takes = [t for t in splits.TRAIN if train_set == "all" or splits.ACTIVITY[t] in LOCO]
    seqs = [splits.load_take(t) for t in takes]
    t0 = time.perf_counter()
    print(f"training {tkeys} on {len(takes)} takes ...", file=sys.stderr, flush=True)
    model = train_model([m.frames for m in seqs], seqs[0].channels, takes, **tkeys)
    print(f"  trained in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    cache.mkdir(parents=True, exist_ok=True)
    model.save(str(path))
    return model, tkeys


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--split", choices=("validation", "test"), default="validation")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--train", choices=("loco", "all"), default="loco")
    ap.add_argument("--setting", action="append", default=[], help="label:key=value,...")
    ap.add_argument("--takes", help="comma-separated subset of the split's takes")
    ap.add_argument("--no-hold", action="store_true")
    ap.add_argument("--cache", default="/tmp/hlmroot_models")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    takes = splits.VALIDATION if args.split == "validation" else splits.TEST
    if args.takes:
        takes = [t for t in args.takes.split(",") if t in takes]
    cases = make_cases(takes, args.seeds)
    acc: dict = defaultdict(lambda: [0.0, 0])
    jumps: dict = defaultdict(list)
    settings = [parse_setting(s) for s in args.setting]
    if not args.no_hold:
        from mocap.baselines import HoldModel

        settings = [("hold", None)] + settings
    for label, opts in settings:
        t0 = time.perf_counter()
        if opts is None:
            from mocap.baselines import HoldModel

            model = HoldModel.fit([cases[0]["truth"]], cases[0]["channels"])
        else:
            base, _ = train(opts, args.train, Path(args.cache))
            inf = {k: v for k, v in opts.items() if k in INFER_KEYS}
            model = base.with_options(**inf) if inf else base
        for c in cases:
            given = np.where(c["obs"], c["truth"], np.nan)
            fill, _ = model.fill_offline(given, c["obs"].copy())
            a = splits.ACTIVITY[c["take"]]
            jumps[(label, a, c["kind"])] += score(c, fill, acc, (label, a, c["kind"]))
        print(f"{label}: {len(cases)} cases in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    rows = []
    for (label, a, kind, metric), (s, n) in sorted(acc.items()):
        if n:
            rows.append(dict(setting=label, activity=a, case=kind, metric=metric, value=float(np.sqrt(s / n)), n=n))
    for (label, a, kind), js in sorted((k, v) for k, v in jumps.items() if v):
        rows.append(dict(setting=label, activity=a, case=kind, metric="jump_cm_median", value=float(np.median(js)),
                         n=len(js)))
    print_table(rows)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"split": args.split, "takes": takes, "seeds": args.seeds, "train": args.train,
                       "settings": [{"label": l, "options": o} for l, o in settings], "rows": rows}, fh, indent=1)
    return 0


def print_table(rows: list[dict]) -> None:
    cols = [("gaps", "body"), ("gaps", "body>=0.5s"), ("gaps+root", "body"), ("gaps+root", "root_cm"),
            ("gaps+root", "yaw_deg"), ("gaps+root", "jump_cm_median"), ("legs-only", "body"),
            ("legs-only", "root_cm"), ("legs-only", "yaw_deg")]
    val = {(r["setting"], r["activity"], r["case"], r["metric"]): r["value"] for r in rows}
    labels = list(dict.fromkeys(r["setting"] for r in rows))
    acts = [a for a in ("walk", "turn", "run", "nonloco") if any(r["activity"] == a for r in rows)]
    print("setting | activity | " + " | ".join(f"{c}:{m}" for c, m in cols))
    for a in acts:
        for lab in labels:
            cells = [f"{val[(lab, a, c, m)]:.2f}" if (lab, a, c, m) in val else "-" for c, m in cols]
            print(f"{lab} | {a} | " + " | ".join(cells))


if __name__ == "__main__":
    sys.exit(main())
