"""`default` on motion its model never saw: each of TRAIN's non-walk activities held out of its own
model in turn (leave one activity out), scored against hold by gap length (bench/notebook/loao-41.md).

VALIDATION's takes all share an activity with TRAIN, so VALIDATION never shows the mixing a motion
neither expert was trained on; this set does, without touching VALIDATION or TEST.  For each group the
model is ``blend.withhlm.train_model`` on TRAIN minus the group (cached in --models), its two experts
remixed with each policy's W/S (refitted by bench/default_hlm_tune.py's ``fit`` on a tuning collection
that tune wrote), and the group's takes erased by the gaps protocol.  ``--validation`` adds VALIDATION's
own takes filled by the full TRAIN model, by activity.

Run (the policy's constants must exist in --root's blend/withhlm.py)::

    OPENBLAS_NUM_THREADS=1 LACUNA_DATA=../shared/data python bench/default_loao.py --root . \\
        --models /tmp/loao --policy P0:0.5:0:15:/tmp/tune/col-z0.5-s30-m24-p1-r1.5.npz \\
        [--groups jumps,runs] [--validation] --seeds 0-4 --json out.json

A policy is NAME:Q_Z:Q_PRIOR_AT:tau:COLLECTION.  Prints, per group and policy, the pooled RMS and each
gap-length bin's RMS against hold's (and the blend alone's), and counts the cells above hold.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

GROUPS: dict[str, list[str]] = {
    "jumps": ["13_39"],
    "subject49": ["49_18"],
    "basketball": [f"basketball_{i}" for i in (1, 2, 3)],
    "signals": [f"basketball_signal_{i}" for i in (1, 2, 3)],
    "soccer": [f"soccer_{i}" for i in (1, 2, 3)],
    "runs": ["35_17", "35_23"],
}


def _seeds(s: str) -> list[int]:
    if "-" in s:
        a, b = s.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(x) for x in s.split(",")]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", default=".", help="the tree whose code runs (its blend/withhlm.py holds the constants)")
    ap.add_argument("--models", required=True, help="directory of the held-out models (trained when absent)")
    ap.add_argument("--policy", action="append", required=True, help="NAME:Q_Z:Q_PRIOR_AT:tau:COLLECTION")
    ap.add_argument("--groups", default=",".join(GROUPS), help="comma-separated groups (default: all)")
    ap.add_argument("--validation", action="store_true", help="also VALIDATION with the full TRAIN model")
    ap.add_argument("--seeds", default="0-4")
    ap.add_argument("--json", help="write every cell's sums here")
    ap.add_argument("--blend-setting", action="append", default=[], metavar="KEY=VALUE",
                    help="change a per-step setting of every model's blend (e.g. vel_shrink=1; bench/notebook/vshr-42.md)")
    a = ap.parse_args(argv)
    root = Path(a.root).resolve()
    sys.path[:0] = [str(root), str(root / "bench")]
    import default_hlm_tune as T  # noqa: E402  (the tree's own fit)

    from blend import withhlm  # noqa: E402
    from lacuna.modelfile import load_model  # noqa: E402
    from mocap import metrics, protocols, splits  # noqa: E402
    from mocap.protocols import GAP_GROUPS  # noqa: E402

    seeds = _seeds(a.seeds)
    models = Path(a.models)
    models.mkdir(parents=True, exist_ok=True)
    policies = []
    for p in a.policy:
        name, qz, pa, tau, col = p.split(":", 4)
        if float(pa) != 0.0 and not hasattr(withhlm, "Q_PRIOR_AT"):
            ap.error(f"{name}: Q_PRIOR_AT is not a constant of {root}/blend/withhlm.py")
        policies.append((name, float(qz), float(pa), float(tau), col))
    jobs: list[tuple[str, list[str], list[str]]] = []  # (group, takes, training takes)
    for g in [x for x in a.groups.split(",") if x]:
        takes = GROUPS[g]
        jobs.append((g, takes, [t for t in splits.TRAIN if t not in takes]))
    if a.validation:
        for act in ("walk", "turn", "run", "nonloco"):
            jobs.append((f"VALIDATION-{act}", [t for t in splits.VALIDATION if splits.ACTIVITY[t] == act], list(splits.TRAIN)))
    cells: dict = {}
    t_start = time.perf_counter()
    for g, takes, train in jobs:
        key = "train" if len(train) == len(splits.TRAIN) else g
        path = models / f"loao-{key}.npz"
        if not path.exists():
            print(f"[{time.perf_counter() - t_start:6.0f} s] training {key} on {len(train)} takes", flush=True)
            withhlm.train_model(protocols.named_training_set(train), fps=120.0).save(str(path))
        m = load_model(str(path))
        if a.blend_setting:
            m.default = m.default.with_settings(**{k: float(v) for k, v in (x.split("=", 1) for x in a.blend_setting)})
        ang = np.array(m.default.ang)
        cases = [c for s in seeds for c in protocols.Gaps(seed=s, split="validation").cases([str(splits.take_path(t)) for t in takes])]
        fills: dict[str, list] = {"blend": [m.default.fill_offline(np.where(c.observed, c.truth, np.nan), c.observed) for c in cases]}
        for name, qz, pa, tau, col in policies:
            withhlm.Q_Z = qz
            if hasattr(withhlm, "Q_PRIOR_AT"):
                withhlm.Q_PRIOR_AT = pa
            W, S = T.fit(dict(np.load(col)), tau)
            mm = withhlm.WithHLMModel(m.default, m.hlm, W, S, {**m.meta, "prior_at": pa}, tau=tau, cal=m.calib, smooth=m.smooth,
                                      rate_ref=m.rate_ref, band_q=m.band_q, band_gate=m.band_gate)
            fills[name] = [mm.fill_offline(np.where(c.observed, c.truth, np.nan), c.observed) for c in cases]
        del ang
        for name, got in fills.items():
            acc = cells.setdefault(g, {}).setdefault(name, {})
            for c, (f, sd) in zip(cases, got):
                v = metrics.values(c, f, sd, c.info.get("groups", GAP_GROUPS))
                for label, keep in _cells(v, metrics):
                    e = acc.setdefault(label, [0.0, 0.0, 0])
                    e[0] += float(np.sum(v.err[keep] ** 2))
                    e[1] += float(np.sum(v.hold_err[keep] ** 2))
                    e[2] += int(keep.sum())
        print(f"[{time.perf_counter() - t_start:6.0f} s] {g}: {len(cases)} cases", flush=True)
        _print(g, cells[g], [p[0] for p in policies])
    if a.json:
        Path(a.json).write_text(json.dumps({"seeds": seeds, "policies": a.policy, "groups": {g: t for g, t, _ in jobs},
                                            "blend_settings": a.blend_setting, "cells": cells, "command": " ".join(sys.argv)}, indent=1))
    print("cells above hold (default RMS > hold RMS), of the novel-motion groups:")
    for name in [p[0] for p in policies] + ["blend"]:
        bad = [(g, lab) for g in cells if not g.startswith("VALIDATION") for lab, (e, h, n) in cells[g][name].items()
               if lab != "all" and n and e > h]
        print(f"  {name}: {len(bad)} {bad}")
    return 0


def _cells(v, metrics):
    n = v.err.size
    yield "all", np.isfinite(v.hold_err) & np.ones(n, bool)
    for lo, hi in metrics.LENGTH_BINS:
        keep = (v.length >= lo) & (v.length < hi) & np.isfinite(v.hold_err)
        if keep.any():
            yield f"len {metrics.bin_label(lo, hi)}", keep
    keep = (v.since < metrics.ONSET_WINDOW_S) & np.isfinite(v.hold_err)
    if keep.any():
        yield f"first {metrics.ONSET_WINDOW_S:g}s", keep


def _print(g: str, acc: dict, names: list[str]) -> None:
    labels = list(acc["blend"])
    print(f"  {g:<18} " + " ".join(f"{lab:>13}" for lab in labels))
    hold = {lab: math.sqrt(acc["blend"][lab][1] / max(acc["blend"][lab][2], 1)) for lab in labels}
    print(f"  {'hold':<18} " + " ".join(f"{hold[lab]:13.2f}" for lab in labels))
    for name in ["blend"] + names:
        row = []
        for lab in labels:
            e, h, n = acc[name][lab]
            r = math.sqrt(e / max(n, 1))
            row.append(f"{r:12.2f}{'*' if e > h else ' '}")
        print(f"  {name:<18} " + " ".join(row))


if __name__ == "__main__":
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    sys.exit(main())
