"""Why the HLM fills one held-out walk worse than another under pan2009's erasure: per channel,
per second since the erasure began, the share of the error that is a constant offset, the
stream-cycle adaptation on and off, and how far each arm channel's swing in the erased half
differs from the half the filter saw.

Trains the HLM as ``lacuna eval --protocol pan2009 --split validation --method hlm`` does (the
paper's training set minus every validation and test take) unless ``--model`` is given, then fills
the split's walks (second half, all but the 14 leg channels erased) causally, with the nearest
neighbour beside it.

    .venv/bin/python bench/hlm_pan2009_diag.py [--split validation] [--model FILE] --out bench/out/pan_diag

Writes OUT.json and OUT.png (the worst channels of the worst take: truth, fill, 2-std band).
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import sys

import numpy as np

from hlm.methods import train_model
from lacuna import registry
from lacuna.modelfile import load_model
from mocap.protocols import Pan2009, wrapped_error

ARM = ("rhumerus.rz", "rhumerus.ry", "rwrist.ry", "lhumerus.rz", "lhumerus.ry", "lwrist.ry")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--split", choices=("validation", "test"), default="validation")
    ap.add_argument("--model")
    ap.add_argument("--out", default="bench/out/pan_diag")
    args = ap.parse_args(argv)
    proto = Pan2009(split=args.split)
    ts = proto.training_set()
    model = load_model(args.model) if args.model else train_model(ts.sequences, ts.channels, ts.names, **proto.options)
    nn_spec = registry.get_method("nn")
    nn = nn_spec.train(ts)
    out: dict = {"split": args.split, "training": ts.names, "takes": {}}
    worst = None
    for case in proto.cases():
        given = np.where(case.observed, case.truth, np.nan)
        t0 = case.info["first_erased"]
        ch = np.array(case.channels)[case.scored]
        fill, std = model.fill_offline(given, case.observed)
        fills = {"hlm": fill, "hlm kappa=0": model.with_options(kappa=0.0, kappa_global=0.0).fill_offline(given, case.observed)[0],
                 "nn": nn_spec.run(nn, given, case.observed.copy())[0]}
        err = {k: wrapped_error(case, f)[t0:, case.scored] for k, f in fills.items()}
        e = err["hlm"]
        per_ch = (e ** 2).mean(0)
        top = np.argsort(-per_ch)[:8]
        T = case.truth.shape[0]
        halves = {}
        for c in ARM:
            if c in case.channels:
                x = case.truth[:, case.channels.index(c)]
                halves[c] = [float(np.ptp(x[:t0])), float(np.ptp(x[t0:]))]
        r = {
            "mse": {k: float(np.mean(v ** 2)) for k, v in err.items()},
            "mse_per_second": [float((e[i : i + 120] ** 2).mean()) for i in range(0, T - t0, 120)],
            "worst_channels": {str(ch[i]): [float(per_ch[i]), float((err["nn"][:, i] ** 2).mean())] for i in top},
            "offset_share": float(((e.mean(0)) ** 2).sum() / per_ch.sum()),
            "arm_swing_p2p_seen_vs_erased": halves,
        }
        r["ratio_to_nn"] = {k: v / r["mse"]["nn"] for k, v in r["mse"].items()}
        out["takes"][case.test] = r
        print(f"{case.test}: " + ", ".join(f"{k} {v:.2f}" for k, v in r["mse"].items())
              + f"; offset share {r['offset_share']:.2f}; arm p2p seen/erased "
              + ", ".join(f"{c} {a:.0f}/{b:.0f}" for c, (a, b) in halves.items()), flush=True)
        if worst is None or r["ratio_to_nn"]["hlm"] > worst[0]:
            worst = (r["ratio_to_nn"]["hlm"], case, fill, std, [str(ch[i]) for i in top[:4]])
    with open(args.out + ".json", "w") as fh:
        json.dump(out, fh, indent=1)
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        _, case, fill, std, names = worst
        fig, ax = plt.subplots(len(names), 1, figsize=(9, 2.2 * len(names)), sharex=True)
        for a, n in zip(ax, names):
            i = case.channels.index(n)
            t = np.arange(case.truth.shape[0])
            a.plot(t, case.truth[:, i], "k", lw=1, label="truth")
            a.plot(t, fill[:, i], "r", lw=1, label="hlm")
            a.fill_between(t, fill[:, i] - 2 * std[:, i], fill[:, i] + 2 * std[:, i], color="r", alpha=0.15, lw=0)
            a.axvline(case.info["first_erased"], color="b", lw=0.8)
            a.set_ylabel(n)
        ax[0].set_title(f"pan2009 {case.test}: worst channels, fill and 2-std band (erased after the blue line)")
        ax[0].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(args.out + ".png", dpi=80)
    except ImportError:
        print("matplotlib missing: no plot", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
