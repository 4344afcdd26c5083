"""Score ``default`` against hold and offline interpolation on one split, with the issue's figures.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/default_eval.py default.npz --split validation \
        [--seeds 0 1 2 3 4] [--extra hlm.npz ...] [--json bench/results/default_eval_test.json]

Occlusion: blend.fit.occlusion (bursts of 0.1-2 s on the six joint groups and the root, seeded;
the gaps protocol's generator plus root dropouts).  Joint angles are scored without the root;
the root is scored apart: translation error in cm (the ASF's length unit converted) and heading.
Figures per activity of mocap.splits.ACTIVITY: RMS degrees by gap length and by time since the
gap began, the first erased frame (median |error| beside the median truth step from the last
observed frame), share of erased values within 1 and 2 std and the Gaussian NLL.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from blend.fit import occlusion  # noqa: E402
from blend.model import group_of, wrap  # noqa: E402
from lacuna.modelfile import load_model  # noqa: E402
from mocap import splits  # noqa: E402
from mocap.baselines import HoldModel, InterpModel  # noqa: E402
from mocap.representation import is_angle  # noqa: E402

GAP_BINS = ((0.1, 0.25), (0.25, 0.5), (0.5, 1.0), (1.0, 2.01))
ONSET_BINS = (("first", 0, 1 / 120 + 1e-9), ("0-50ms", 0, 0.05), ("50-100ms", 0.05, 0.1), ("0.1-0.25s", 0.1, 0.25),
              ("0.25-0.5s", 0.25, 0.5), ("0.5-1s", 0.5, 1.0), ("1-2s", 1.0, 2.01))


def runs(miss: np.ndarray):
    """Per value of a (T, C) mask: frames since the run began (1 = first) and the run's length."""
    T, C = miss.shape
    k = np.zeros((T, C), int)
    length = np.zeros((T, C), int)
    for c in range(C):
        d = np.diff(np.concatenate([[0], miss[:, c].astype(int), [0]]))
        for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)):
            k[a:b, c] = np.arange(1, b - a + 1)
            length[a:b, c] = b - a
    return k, length


def rms(x):
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("model")
    ap.add_argument("--split", choices=["validation", "test"], required=True)
    ap.add_argument("--seeds", type=int, nargs="+", default=None)
    ap.add_argument("--extra", nargs="*", default=[], help="more causal model files to score beside it")
    ap.add_argument("--json")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="override a run-time setting of the default model (exploration on validation only)")
    args = ap.parse_args()
    seeds = args.seeds or ([100, 101, 102] if args.split == "validation" else [0, 1, 2, 3, 4])
    takes = splits.SPLITS[args.split]
    train = [splits.load_take(t).frames for t in splits.TRAIN]
    first = splits.load_take(takes[0])
    ch = first.channels
    hold = HoldModel.fit(train, ch)
    methods = {"hold": hold, "interp": InterpModel(ch, hold.mean_, hold.std_), "default": load_model(args.model)}
    for kv in args.set:
        k, v = kv.split("=", 1)
        setattr(methods["default"].settings, k, float(v))
        methods["default"] = methods["default"].with_weights(methods["default"].weights)  # re-derive per-frame constants
    for p in args.extra:
        methods[Path(p).stem] = load_model(p)
    ang = np.array([is_angle(c) for c in ch])
    grp = np.array([group_of(c) for c in ch])
    joint = ang & (grp != 0)
    tpos = [ch.index(c) for c in ("root.tx", "root.ty", "root.tz")]
    yaw = ch.index("root.ry")
    acc: dict = {}
    for take in takes:
        m = splits.load_take(take)
        unit_cm = 2.54 / float(m.skeleton.units.get("length", 0.45)) if m.skeleton else 1.0
        act = splits.ACTIVITY[take]
        truth = m.frames
        for seed in seeds:
            obs, _ = occlusion(take, truth.shape[0], ch, m.fps, seed)
            miss = ~obs
            k, length = runs(miss)
            given = np.where(obs, truth, np.nan)
            jm = miss & joint[None]
            step = np.zeros_like(truth)
            step[1:] = np.abs(wrap(truth[1:] - truth[:-1]))
            rec = acc.setdefault(act, {"k": [], "len": [], "step": [], "err": {}, "std": [], "root": {}, "yaw": {}})
            rec["k"].append(k[jm]); rec["len"].append(length[jm]); rec["step"].append(step[jm])
            rmiss = miss[:, tpos[0]]
            for name, model in methods.items():
                fill, std = (model.fill_offline(given, obs) if name != "interp" else model.fill_offline(given, obs))
                e = wrap(fill - truth)
                rec["err"].setdefault(name, []).append(e[jm])
                if name == "default":
                    rec["std"].append(std[jm])
                pe = (fill[:, tpos] - truth[:, tpos]) * unit_cm
                rec["root"].setdefault(name, []).append(np.linalg.norm(pe[rmiss], axis=1))
                rec["yaw"].setdefault(name, []).append(e[rmiss, yaw])
        print(f"  {take} ({act}) done", file=sys.stderr, flush=True)
    out = {"split": args.split, "takes": takes, "seeds": seeds, "activities": {}}
    names = list(methods)
    for act, rec in sorted(acc.items()):
        k = np.concatenate(rec["k"]); ln = np.concatenate(rec["len"]) / 120.0; step = np.concatenate(rec["step"])
        err = {n: np.concatenate(v) for n, v in rec["err"].items()}
        std = np.concatenate(rec["std"])
        t = k / 120.0
        a = {"values": int(len(k)), "all": {n: rms(err[n]) for n in names}}
        a["gap_length"] = {f"{lo:g}-{min(hi, 2):g}s": {n: rms(err[n][(ln >= lo) & (ln < hi)]) for n in names} for lo, hi in GAP_BINS}
        a["gap_length"][">=0.5s"] = {n: rms(err[n][ln >= 0.5]) for n in names}
        a["since_onset"] = {lab: {n: rms(err[n][(t > lo) & (t <= hi)]) for n in names} for lab, lo, hi in ONSET_BINS}
        f1 = k == 1
        a["first_frame"] = {"median_truth_step": float(np.median(step[f1])),
                            **{f"median_err_{n}": float(np.median(np.abs(err[n][f1]))) for n in names}}
        a["first_100ms_rms"] = {n: rms(err[n][t <= 0.1]) for n in names}
        z = np.abs(err["default"]) / np.maximum(std, 1e-9)
        a["calibration"] = {"within_1std": float(np.mean(z <= 1)), "within_2std": float(np.mean(z <= 2)),
                            "nll": float(np.mean(0.5 * z**2 + np.log(np.maximum(std, 1e-9)) + 0.5 * np.log(2 * np.pi)))}
        a["root_cm"] = {n: rms(np.concatenate(v)) for n, v in rec["root"].items()}
        a["heading_deg"] = {n: rms(np.concatenate(v)) for n, v in rec["yaw"].items()}
        out["activities"][act] = a
    print(format_tables(out, names))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


def format_tables(out, names) -> str:
    L = [f"split {out['split']} ({', '.join(out['takes'])}), seeds {out['seeds']}; RMS degrees over erased joint angles"]
    acts = out["activities"]
    for key in ("gap_length", "since_onset"):
        L.append(f"\n| {key} | " + " | ".join(f"{a}: " + "/".join(names) for a in acts) + " |")
        L.append("|---" * (len(acts) + 1) + "|")
        for b in next(iter(acts.values()))[key]:
            L.append(f"| {b} | " + " | ".join("/".join(f"{acts[a][key][b][n]:.2f}" for n in names) for a in acts) + " |")
    L.append("\n| activity | all (" + "/".join(names) + ") | first frame: truth step, " + "/".join(names)
             + " | first 100 ms RMS | within 1 / 2 std, NLL | root cm | heading deg |")
    L.append("|---|---|---|---|---|---|---|")
    for a, d in acts.items():
        ff = d["first_frame"]
        L.append(f"| {a} | " + "/".join(f"{d['all'][n]:.2f}" for n in names)
                 + f" | {ff['median_truth_step']:.3f}; " + "/".join(f"{ff['median_err_' + n]:.3f}" for n in names)
                 + " | " + "/".join(f"{d['first_100ms_rms'][n]:.3f}" for n in names)
                 + f" | {d['calibration']['within_1std']:.3f} / {d['calibration']['within_2std']:.3f}, {d['calibration']['nll']:.2f}"
                 + " | " + "/".join(f"{d['root_cm'][n]:.1f}" for n in names)
                 + " | " + "/".join(f"{d['heading_deg'][n]:.2f}" for n in names) + " |")
    return "\n".join(L)


if __name__ == "__main__":
    sys.exit(main())
