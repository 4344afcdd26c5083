"""``default`` with and without the guard (blend/guard.py) against hold, on the gaps protocol's cases.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/default_guard.py --split validation --seeds 0-4 \
        --variant off '{"guard_s": 0}' --variant g4 '{"guard_s": 4}' [--json OUT.json]

The Gaussian on mocap.splits.TRAIN, the shipped weights (blend/weights.json) with each variant's
settings laid over the shipped ones; every case of ``lacuna eval --protocol gaps`` (its masks, its
seeds) filled causally frame by frame.  Per activity: RMS degrees over erased angles, by time since
onset and by gap length (the bins of mocap.metrics), the root's angles, the share within 2 std, and
each cell's ratio to hold; cells above hold are listed.  Choose on ``--split validation`` only.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from blend.fit import collect, fit_weights  # noqa: E402
from blend.model import GROUP_NAMES, DefaultModel, Settings, Weights  # noqa: E402
from blend.train import SEEDS, train_model  # noqa: E402
from mocap import (
    metrics,  # noqa: E402
    splits,  # noqa: E402
)
from mocap.protocols import GAP_GROUPS, Gaps  # noqa: E402


def stream_fill(model, frames, obs):
    st = model.stream()
    out = np.empty_like(frames)
    std = np.zeros_like(frames)
    for t in range(frames.shape[0]):
        f = st.step(np.where(obs[t], frames[t], np.nan), obs[t])
        out[t], std[t] = f.frame, f.std
    return out, std


def hold_fill(frames, obs):
    out = np.empty_like(frames)
    last = frames[0].copy()
    for t in range(frames.shape[0]):
        last = np.where(obs[t], frames[t], last)
        out[t] = last
    return out


def variant(base: DefaultModel, over: dict, weights=None) -> DefaultModel:
    s = Settings(**{**base.settings.__dict__, **over})
    return DefaultModel(base.channels, base.mean_, base.std_, base.reg_idx, base.mu_, base.cov_, s,
                        base.weights if weights is None else weights, base.meta, base.vrms_, base.vgain_)


def fold_weights(base: DefaultModel) -> tuple[dict[str, int], list]:
    """Two folds of VALIDATION by take (alternating within activity, as bench/default_tune.py): each
    fold's weights fitted (blend.fit, seeds 100-102, guard off) on the other fold's takes."""
    val = [(t, splits.load_take(t).frames, splits.ACTIVITY[t]) for t in splits.VALIDATION]
    fold = {}
    for a in sorted({v[2] for v in val}):
        for i, v in enumerate([v for v in val if v[2] == a]):
            fold[v[0]] = i % 2
    probe = variant(base, {"guard_s": 0.0}, Weights.initial(len(GROUP_NAMES), len(base.knots)))
    ws = [fit_weights(probe, collect(probe, [v for v in val if fold[v[0]] != f], SEEDS)) for f in (0, 1)]
    return fold, ws


SHOW = ("rms_deg[group root]", "within_2std", "onset_err_over_step", "rms_deg[first 0.1s]", "hold_rms_deg[first 0.1s]",
        "root_pos_rms_cm", "hold_root_pos_rms_cm")


def _f(v) -> str:
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.2f}"


def plot(table, names, acts, out: Path, title: str) -> None:
    """RMS / hold by time since onset, one panel per activity, one line per variant (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bins = ["since first", "since 0-0.05s", "since 0.05-0.1s", "since 0.1-0.25s", "since 0.25-0.5s", "since 0.5-1s",
            "since 1-2s"]
    fig, axes = plt.subplots(1, len(acts), figsize=(4 * len(acts), 3.4), sharey=True)
    for ax, a in zip(np.atleast_1d(axes), acts):
        h = table[f"hold|{a}"]
        for n in names[1:]:
            d = table[f"{n}|{a}"]
            y = [d.get(f"rms_deg[{b}]") / h[f"rms_deg[{b}]"] if d.get(f"rms_deg[{b}]") and h.get(f"rms_deg[{b}]")
                 else np.nan for b in bins]
            ax.plot(range(len(bins)), y, marker="o", label=n)
        ax.axhline(1.0, color="k", lw=0.8)
        ax.set_xticks(range(len(bins)), [b[6:] for b in bins], rotation=45, fontsize=7)
        ax.set_title(a)
    np.atleast_1d(axes)[0].set_ylabel("RMS / hold")
    np.atleast_1d(axes)[-1].legend(fontsize=7)
    fig.suptitle(f"default vs hold by time since onset: {title}", fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    print(f"wrote {out}")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--split", default="validation", choices=("validation", "test"))
    ap.add_argument("--seeds", default="0-4")
    ap.add_argument("--variant", nargs=2, action="append", metavar=("NAME", "JSON"), default=[])
    ap.add_argument("--folds", action="store_true", help="VALIDATION only: each take scored with weights fitted on "
                    "the other half of VALIDATION (the shipped weights saw every validation take)")
    ap.add_argument("--json")
    args = ap.parse_args()
    a, _, b = args.seeds.partition("-")
    seeds = list(range(int(a), int(b or a) + 1))
    variants = args.variant or [["shipped", "{}"]]
    seqs = [splits.load_take(t).frames for t in splits.TRAIN]
    ch = splits.load_take(splits.TRAIN[0]).channels
    base = train_model(seqs, ch, splits.TRAIN)
    if args.folds:
        if args.split != "validation":
            ap.error("--folds scores VALIDATION only")
        fold, ws = fold_weights(base)
        per_fold = [{n: variant(base, json.loads(o), ws[f]) for n, o in variants} for f in (0, 1)]
    else:
        models = {n: variant(base, json.loads(o)) for n, o in variants}
    vals: dict = {}  # (name, activity) -> [metrics.Values]
    for seed in seeds:
        for case in Gaps(seed, args.split).cases():
            act = splits.ACTIVITY[case.test]
            if args.folds:
                models = per_fold[fold[case.test]]
            fills = {"hold": (hold_fill(case.truth, case.observed), None)}
            fills.update({n: stream_fill(m, case.truth, case.observed) for n, m in models.items()})
            for n, (fill, std) in fills.items():
                vals.setdefault((n, act), []).append(metrics.values(case, fill, std, case.info.get("groups", GAP_GROUPS)))
        print(f"seed {seed} done", flush=True)
    names = ["hold"] + [v[0] for v in variants]
    acts = sorted({a for _, a in vals})
    table = {f"{n}|{a}": {m: v for m, v, _ in metrics.summarise(metrics.Values.concat(vals[(n, a)]))}
             for n in names for a in acts}
    keys = [k for k in table[f"hold|{acts[0]}"] if k.startswith("rms_deg") and "group" not in k or k in SHOW]
    keys += [k for k in SHOW if k not in keys]
    print("| metric | " + " | ".join(f"{a}: " + " / ".join(names) for a in acts) + " |\n|---|" + "---|" * len(acts))
    for k in keys:
        print(f"| {k} | " + " | ".join(" / ".join(_f(table[f'{n}|{a}'].get(k)) for n in names) for a in acts) + " |")
    for n in names[1:]:
        bad = [(a, k, table[f"{n}|{a}"][k] / table[f"hold|{a}"][k]) for a in acts for k in keys if k.startswith("rms_deg")
               and table[f"{n}|{a}"].get(k) is not None and table[f"hold|{a}"].get(k) and table[f"{n}|{a}"][k] > table[f"hold|{a}"][k]]
        print(f"{n}: {len(bad)} cells above hold: " + ", ".join(f"{a} {k[8:-1]} {r:.3f}" for a, k, r in bad))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"split": args.split, "seeds": seeds, "variants": variants, "folds": args.folds,
                                               "takes": list(splits.SPLITS[args.split]), "figures": table}, indent=1) + "\n")
        plot(table, names, acts, Path(args.json).with_suffix(".png"), f"{args.split}{' (2 folds)' if args.folds else ''}, seeds {args.seeds}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
