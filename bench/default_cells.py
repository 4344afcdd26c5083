"""``default`` against hold per activity x joint group x time since onset, on VALIDATION.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/default_cells.py [--cache /tmp/default_val.npz] [--targets 1.0 0.95]

The Gaussian on mocap.splits.TRAIN, the shipped settings; the stream over the VALIDATION takes with
blend.fit's occlusions (seeds 100-102, the weights' own); for every weight fit compared (the
shipped weights.json, and fit_weights refitted with boost cells pooled over groups, the root
angles' own (the default) and every group's own) it prints RMS(default) / RMS(hold) of every
(activity, group, bin) cell with at least 200 erased values that is above 1, scored two ways:
in-sample (weights fitted on all validation takes) and 2-fold by take (the weights fitted on the
other half).  No TEST or paper-test take is read.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from default_tune import BINS, offline_fill, subset  # noqa: E402

from blend.fit import collect, fit_gaussian, fit_weights, velocity_gain, velocity_rms  # noqa: E402
from blend.model import GROUP_NAMES, DefaultModel  # noqa: E402
from blend.train import SEEDS, shipped  # noqa: E402
from mocap import splits  # noqa: E402


def cells(model, data, w, min_n=200):
    """{(activity, group, bin): (rms ratio default/hold, n)}"""
    fill = offline_fill(model, data, w)
    e2, h2 = (data["y"] - fill) ** 2, (data["y"] - data["H"]) ** 2
    out = {}
    for ai, a in enumerate(data["activities"]):
        for g, gn in enumerate(GROUP_NAMES):
            for lo, hi in BINS:
                s = (data["act"] == ai) & (data["g"] == g) & (data["k"] > lo) & (data["k"] <= hi)
                if s.sum() >= min_n:
                    out[(str(a), gn, f"{lo}-{hi}f")] = (float(np.sqrt(e2[s].mean() / max(h2[s].mean(), 1e-12))), int(s.sum()))
    return out


def report(title, c):
    bad = {k: v for k, v in c.items() if v[0] > 1.0}
    print(f"{title}: {len(bad)} of {len(c)} cells worse than hold" + (":" if bad else ""))
    for k, (r, n) in sorted(bad.items(), key=lambda kv: -kv[1][0]):
        print(f"   {k[0]:8s} {k[1]:10s} {k[2]:9s} {r:.3f}  (n={n})")


def load(cache: str | None):
    s, w, _ = shipped()
    train = [splits.load_take(t).frames for t in splits.TRAIN]
    ch = splits.load_take(splits.TRAIN[0]).channels
    model = DefaultModel(ch, *fit_gaussian(train, ch, s), s, w, vrms=velocity_rms(train, ch),
                         vgain=velocity_gain(train, ch, s) if s.vel_gain else None)
    if cache and Path(cache).exists():
        z = np.load(cache, allow_pickle=False)
        data = {k: z[k] for k in z.files}
    else:
        val = [(t, splits.load_take(t).frames, splits.ACTIVITY[t]) for t in splits.VALIDATION]
        data = collect(model, val, SEEDS)
        if cache:
            np.savez(cache, **data)
    return model, data


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cache")
    ap.add_argument("--targets", type=float, nargs="+", default=[1.0, 0.95, 0.9])
    ap.add_argument("--rounds", type=int, default=40)
    args = ap.parse_args()
    model, data = load(args.cache)
    s, w, _ = shipped()
    report("shipped weights, in-sample", cells(model, data, w))
    # two folds by take, alternating within each activity (as bench/default_tune.py)
    tk = np.unique(data["take"])
    act_of = {t: int(data["act"][np.argmax(data["take"] == t)]) for t in tk}
    rank = {t: sum(1 for u in tk if u < t and act_of[u] == act_of[t]) for t in tk}
    fold = np.array([rank[t] % 2 for t in range(int(tk.max()) + 1)])[data["take"]]
    for label, per_group in (("pooled", ()), ("root angles", (0,)), ("every group", tuple(range(len(GROUP_NAMES))))):
        for target in args.targets:
            name = f"refit, own cells: {label}, target={target} rounds={args.rounds}"
            wi = fit_weights(model, data, per_group=per_group, target=target, rounds=args.rounds)
            report(name + ", in-sample", cells(model, data, wi))
            cv = {}
            for f in (0, 1):
                wf = fit_weights(model, subset(data, fold != f), per_group=per_group, target=target, rounds=args.rounds)
                for k, v in cells(model, subset(data, fold == f), wf).items():
                    cv.setdefault(k, []).append(v)
            cvm = {k: (float(np.sqrt(np.sum([r * r * n for r, n in v]) / np.sum([n for _, n in v]))), int(sum(n for _, n in v)))
                   for k, v in cv.items()}
            report(name + ", 2-fold", cvm)
            per = overall(model, data, wi)
            print("   in-sample MSE/hold per activity: " + " ".join(f"{a} {r:.3f}" for a, r in per.items()))
    return 0


def overall(model, data, w):
    fill = offline_fill(model, data, w)
    e2, h2 = (data["y"] - fill) ** 2, (data["y"] - data["H"]) ** 2
    return {str(a): float(e2[data["act"] == i].mean() / h2[data["act"] == i].mean()) for i, a in enumerate(data["activities"])}


if __name__ == "__main__":
    sys.exit(main())
