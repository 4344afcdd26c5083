"""The section-5 fill-in experiment on taylor2007: faithful CRBM against improvements and the
nearest-neighbour baselines.  Writes JSON (and prints a markdown table for docs/BENCHMARKS.md).

    .venv/bin/python bench/crbm_taylor2007.py --out bench/results/crbm_taylor2007.json

Variants (name: training options | fill options):
  faithful    ``crbm``: trained as Taylor's released code (crbm.released.RELEASED: history noise 1,
              hidden probabilities in the data term, biases from N(0, 0.01^2), fixed mini-batches) on
              its input (raw root channels, crbm.released.RELEASED_INPUT)
              | K=30, S=1 Gibbs; "-S8": S=8 chains averaged; "-mf": deterministic mean-field fill
  paper-text  what ``crbm`` was before 2026-12-01 (crbm.released.PAPER_TEXT: history noise 0,
              sampled hiddens in the data term, zero biases, reshuffled mini-batches) | S=1, S=8, mean-field
  imcrbm      paper-text + history noise 1 | S=1, S=8, mean-field
  prob        paper-text + hidden probabilities in the data term | S=1, S=8, mean-field
  imp         prob + parameters averaged over the last 20% of epochs | S=1, S=8 (= ``crbm-imp``), mean-field
  ens         three ``imp`` CRBMs (seeds s, s+1000, s+2000; 1300 epochs each) filling together from
              one shared history (= ``crbm-ens``) | S=4 per member (the default), S=8, mean-field
  2level      ``crbm-2level``: paper-text first level + second level on its hidden activities | S=1, S=8, mean-field
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from crbm.experiment import ANCHOR_METRIC, METRIC, baseline_scores, ratios, score_model, table  # noqa: E402
from crbm.released import PAPER_TEXT, RELEASED_INPUT  # noqa: E402
from crbm.train import train_model  # noqa: E402
from mocap.protocols import get_protocol  # noqa: E402


def anchor_runs(a: argparse.Namespace) -> int:
    """--octave-model / --anchor-input: everything on the Octave anchor's own input (crbm.anchor)."""
    from crbm import anchor
    from crbm.model import CRBM
    from crbm.released import RELEASED

    data = anchor.anchor_data()
    circ = get_protocol("taylor2007").train_variance()
    runs: dict = {}
    if a.octave_model:
        todo = [(f"released weights {os.path.basename(p)}", lambda p=p: anchor.load_octave_model(p)) for p in a.octave_model]
    else:
        kw = {"faithful": RELEASED, "paper-text": PAPER_TEXT}
        todo = [(f"{v} on the anchor's input (seed {s})",
                 lambda v=v, s=s: CRBM(n_hidden=150, order=3, n_epochs=a.epochs or 2000, random_state=s, **kw[v]).fit(
                     data["sequences"])) for v in a.variants for s in a.seeds]
    for name, make in todo:
        t0 = time.perf_counter()
        crbm = make()
        secs = time.perf_counter() - t0
        sc = anchor.score(crbm, data, repeats=a.repeats, circular_var=circ)
        runs[name] = {"seconds": round(secs, 1), "scores": {f"{t} {g}": v for (t, g), v in sc.items()}}
        print(f"{name} ({secs:.0f} s): " + ", ".join(
            f"{t} {g} {v['plain_var']:.2f} +-{v['plain_var std']:.2f} (protocol's variance {v['protocol']:.2f})"
            for (t, g), v in sorted(sc.items())), flush=True)
    if a.out:
        os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
        with open(a.out, "w") as fh:
            json.dump({"repeats": a.repeats, "runs": runs}, fh, indent=2)
    return 0


def octave_fill_runs(a: argparse.Namespace) -> int:
    """--octave-fills: the released code's own fills (saved .mat) through crbm.anchor.cumulative_scaled."""
    import numpy as np

    from crbm import anchor

    data = anchor.anchor_data()
    runs = {}
    for p in a.octave_fills:
        sc = anchor.octave_fills(p, data)
        runs[os.path.basename(p)] = {f"{t} {g}": {"mean": float(np.mean(v)), "std": float(np.std(v, ddof=1)), "runs": v}
                                     for (t, g), v in sorted(sc.items())}
        print(f"{os.path.basename(p)}: " + ", ".join(f"{t} {g} {np.mean(v):.2f} +-{np.std(v, ddof=1):.2f} ({len(v)} fills)"
                                                     for (t, g), v in sorted(sc.items())), flush=True)
    md = compare_table(runs, a.compare) if a.compare else ""
    print(md)
    if a.out:
        os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
        with open(a.out, "w") as fh:
            json.dump({"scorer": "crbm.anchor.cumulative_scaled, plain training variance", "runs": runs, "table": md},
                      fh, indent=2)
    return 0


def compare_table(octave: dict, ours_json: list[str]) -> str:
    """Markdown: per case, the released code's fills (one column per saved .mat = training seed)
    and ours (every variant run of the given bench JSONs), each the mean of its fills on the one
    scorer; then the mean and std over training seeds and ours / released."""
    import numpy as np

    from crbm.experiment import ANCHOR_METRIC

    ours: dict[str, dict[str, float]] = {}
    for path in ours_json:
        with open(path) as fh:
            for name, v in json.load(fh)["variants"].items():
                ours[name] = {k: sc[ANCHOR_METRIC] for k, sc in v["scores"].items()}
    cases = sorted(next(iter(octave.values())))
    lines = ["| case | released code, per seed | mean +- std (seeds) | ours, per seed | mean +- std (seeds) | ours / released |",
             "|---|---|---|---|---|---|"]
    for c in cases:
        r = [v[c]["mean"] for v in octave.values()]
        o = [v[c] for v in ours.values()]
        lines.append(f"| {c} | {' / '.join(f'{x:.2f}' for x in r)} | {np.mean(r):.2f} +- {np.std(r, ddof=1):.2f} | "
                     f"{' / '.join(f'{x:.2f}' for x in o)} | {np.mean(o):.2f} +- {np.std(o, ddof=1):.2f} | "
                     f"{np.mean(o) / np.mean(r):.3f} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--epochs", type=int, default=None, help="default: 2000 (the released demo)")
    ap.add_argument("--repeats", type=int, default=10, help="stochastic fills averaged per case")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="training seeds")
    ap.add_argument("--variants", nargs="+", default=["faithful", "imcrbm", "2level"])
    ap.add_argument("--bias-rates", type=float, nargs="+", default=[0.0],
                    help="fill: per-stream bias adaptation rates to score each model with (crbm.filler; default 0)")
    ap.add_argument("--fills", nargs="+", default=["S1", "S8", "mf"], choices=["S1", "S8", "mf"],
                    help="fills scored per model: the variant's default chains, 8 chains, mean field")
    ap.add_argument("--root-mode", choices=["relative", "raw"], default=None,
                    help="the representation's root: body-centred (the paper) or raw channels; default: "
                    "the variant's own (faithful: raw, as the released code's input; the others: body-centred)")
    ap.add_argument("--octave-fills", nargs="+", default=[], metavar="MAT",
                    help="score fills saved by the anchor's crbmfill_save.m with the one scorer (crbm.anchor), then exit")
    ap.add_argument("--anchor-input", action="store_true",
                    help="train on the Octave anchor's input instead (raw channels z-scored, no unwrapping; "
                    "crbm.anchor) and score as its crbmfill.m does; variants 'faithful' and 'paper-text' only")
    ap.add_argument("--octave-model", nargs="+", default=[], metavar="MAT",
                    help="score models trained by the anchor's train.m with our filler on its input, then exit")
    ap.add_argument("--compare", nargs="+", default=[], metavar="JSON",
                    help="with --octave-fills: a table of those against our runs saved by this script's --out")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    if a.octave_fills:
        return octave_fill_runs(a)
    if a.octave_model or a.anchor_input:
        return anchor_runs(a)
    ts = get_protocol("taylor2007").training_set()
    base = baseline_scores()
    named = dict(base)
    results: dict = {"machine": f"{platform.machine()} {platform.processor() or ''} {os.cpu_count()} cores, "
                                f"python {platform.python_version()}", "repeats": a.repeats, "variants": {}}
    train_kw = {"faithful": dict(RELEASED_INPUT), "paper-text": PAPER_TEXT, "imcrbm": {**PAPER_TEXT, "history_noise": 1.0},
                "2level": {**PAPER_TEXT, "levels": 2, "final_step": "input"},
                "prob": {**PAPER_TEXT, "positive_hidden": "prob"},
                "imp": {**PAPER_TEXT, "positive_hidden": "prob", "average_last": 0.2, "final_step": "input"},
                "ens": {**PAPER_TEXT, "positive_hidden": "prob", "average_last": 0.2, "members": 3, "final_step": "input"}}
    for v in a.variants:
        for seed in a.seeds:
            t0 = time.perf_counter()
            model = train_model(ts.sequences, ts.channels, epochs=a.epochs, seed=seed, progress=True,
                                progress_every=500, **{"root_mode": "relative", **train_kw[v],
                                                       **({"root_mode": a.root_mode} if a.root_mode else {})})
            secs = time.perf_counter() - t0
            fills = [("", {"n_chains": 4 if v == "ens" else 1, "mode": "gibbs"}, "S1"),
                     ("-S8", {"n_chains": 8, "mode": "gibbs"}, "S8"), ("-mf", {"n_chains": 1, "mode": "mean-field"}, "mf")]
            fills = [(suffix, fk) for suffix, fk, key in fills if key in a.fills]
            for (suffix, fk), br in ((f, b) for f in fills for b in a.bias_rates):
                model.set_chains(fk["n_chains"])
                model.set_mode(fk["mode"])
                model.bias_rate = br
                # the same fill sampler seeds 0..repeats-1 for every trained model, as the anchor
                sc = score_model(model, repeats=1 if fk["mode"] == "mean-field" else a.repeats, seed=0)
                name = f"{v}{suffix}{f' r={br:g}' if br else ''} (seed {seed})"
                named[name] = sc
                r = ratios(sc, base)
                results["variants"][name] = {"train_seconds": secs, "epochs": model.meta["training"]["epochs"],
                                             "scores": {f"{t} {e}": s for (t, e), s in sc.items()},
                                             "ratio_to_better_nn": {f"{t} {e}": x for (t, e), x in r.items()}}
                print(f"{name}: trained {secs:.1f} s; " + ", ".join(
                    f"{t} {e} {sc[(t, e)][METRIC]:.2f} +-{sc[(t, e)][METRIC + ' std']:.2f} (x{r[(t, e)]:.2f}; "
                    f"plain-variance {sc[(t, e)][ANCHOR_METRIC]:.2f} +-{sc[(t, e)][ANCHOR_METRIC + ' std']:.2f})"
                    for (t, e) in sorted(sc)), file=sys.stderr, flush=True)
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
