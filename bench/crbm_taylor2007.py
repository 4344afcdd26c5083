"""The section-5 fill-in experiment on taylor2007: faithful CRBM against improvements and the
nearest-neighbour baselines.  Writes JSON (and prints a markdown table for docs/BENCHMARKS.md).

    .venv/bin/python bench/crbm_taylor2007.py --out bench/results/crbm_taylor2007.json

Variants (name: training options | fill options):
  faithful    the paper: history noise 0, sampled hiddens in the data term | K=30, S=1 Gibbs
  faithful-mf same model | deterministic mean-field fill
  faithful-S8 same model | K=30, S=8 chains averaged
  imcrbm      history noise 1 (Taylor's imCRBM code) | S=1, S=8, mean-field
  prob        hidden probabilities in the data term (the released code) | S=1, S=8, mean-field
  imp         prob + parameters averaged over the last 20% of epochs | S=1, S=8 (= ``crbm-imp``), mean-field
  ens         three ``imp`` CRBMs (seeds s, s+1000, s+2000; 1300 epochs each) filling together from
              one shared history (= ``crbm-ens``) | S=4 per member (the default), S=8, mean-field
  2level      faithful first level + second level on its hidden activities | S=1, S=8, mean-field
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from crbm.experiment import METRIC, baseline_scores, ratios, score_model, table  # noqa: E402
from crbm.train import train_model  # noqa: E402
from mocap.protocols import get_protocol  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--epochs", type=int, default=None, help="default: 2000 (the released demo)")
    ap.add_argument("--repeats", type=int, default=10, help="stochastic fills averaged per case")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="training seeds")
    ap.add_argument("--variants", nargs="+", default=["faithful", "imcrbm", "2level"])
    ap.add_argument("--bias-rates", type=float, nargs="+", default=[0.0],
                    help="fill: per-stream bias adaptation rates to score each model with (crbm.filler; default 0)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    ts = get_protocol("taylor2007").training_set()
    base = baseline_scores()
    named = dict(base)
    results: dict = {"machine": f"{platform.machine()} {platform.processor() or ''} {os.cpu_count()} cores, "
                                f"python {platform.python_version()}", "repeats": a.repeats, "variants": {}}
    train_kw = {"faithful": {}, "imcrbm": {"history_noise": 1.0}, "2level": {"levels": 2},
                "prob": {"positive_hidden": "prob"}, "imp": {"positive_hidden": "prob", "average_last": 0.2},
                "ens": {"positive_hidden": "prob", "average_last": 0.2, "members": 3}}
    for v in a.variants:
        for seed in a.seeds:
            t0 = time.perf_counter()
            model = train_model(ts.sequences, ts.channels, epochs=a.epochs, seed=seed, progress=True,
                                progress_every=500, **train_kw[v])
            secs = time.perf_counter() - t0
            fills = [("", {"n_chains": 4 if v == "ens" else 1, "mode": "gibbs"}),
                     ("-S8", {"n_chains": 8, "mode": "gibbs"}), ("-mf", {"n_chains": 1, "mode": "mean-field"})]
            for (suffix, fk), br in ((f, b) for f in fills for b in a.bias_rates):
                model.set_chains(fk["n_chains"])
                model.set_mode(fk["mode"])
                model.bias_rate = br
                sc = score_model(model, repeats=1 if fk["mode"] == "mean-field" else a.repeats, seed=seed)
                name = f"{v}{suffix}{f' r={br:g}' if br else ''} (seed {seed})"
                named[name] = sc
                r = ratios(sc, base)
                results["variants"][name] = {"train_seconds": secs, "epochs": model.meta["training"]["epochs"],
                                             "scores": {f"{t} {e}": s for (t, e), s in sc.items()},
                                             "ratio_to_better_nn": {f"{t} {e}": x for (t, e), x in r.items()}}
                print(f"{name}: trained {secs:.1f} s; " + ", ".join(
                    f"{t} {e} {sc[(t, e)][METRIC]:.2f} (x{r[(t, e)]:.2f})" for (t, e) in sorted(sc)), file=sys.stderr, flush=True)
    results["baselines"] = {n: {f"{t} {e}": s for (t, e), s in sc.items()} for n, sc in base.items()}
    md = table(named)
    print(md)
    if a.out:
        os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
        with open(a.out, "w") as fh:
            json.dump({**results, "table": md}, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
