"""loco-12's regime check (bench/notebook/loco-12.md, rule item 7): the leg gate (blend/withhlm.py,
"Long erasures") where it acts, on VALIDATION takes only: pan2009's pattern (every channel but the legs
erased from half way) on each VALIDATION take, and the stress bench's splices (bench/default_stress.py:
a walk's first 5 s, then a non-locomotion take) erased but the legs from 30 frames after the seam.
MSE (deg^2) over the erased angles of ``default`` per model file given, its blend alone and hold.
``--split test`` (only after a choice, reported, never used to choose): the same on TEST's takes, the
splices' walks TEST's walking_27, walking_28 and 35_30 (fixed before the run, as VALIDATION's two
walking_ takes and one of subject 35).

``--set loco13`` (bench/notebook/loco-13.md, fixed before any of its bounds was chosen): the larger regime
set: pan2009's pattern on each take of the split as above, and every walk -> non-locomotion splice whose
first half is any of the split's locomotion takes (walk, turn, run) and second any of its non-locomotion
takes, erased but the legs from 30, 90 and 240 frames after the seam (case ``W+T@N``).  ``--ll D,TAU`` (any
number): each model file also with long_ll (D, TAU) set in-process (blend/withhlm.py), named ``STEM_llD_TAU``;
``--ll D,TAU,legs`` (loco-14): with long_ll_legs (the legs-only baseline), named ``STEM_llD_TAU_legs``.

    OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/loco12_regime.py OFF.npz ON.npz [--split test] [--set loco13] [--ll 4,30] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.default_stress import splice  # noqa: E402
from blend import withhlm  # noqa: E402
from lacuna import modelfile  # noqa: E402
from mocap import protocols, splits  # noqa: E402
from mocap.representation import is_angle  # noqa: E402
from mocap.rootrot import wrap180 as wrap  # noqa: E402

SPLICE_WALKS = ("walking_20", "walking_21", "35_28")
SPLICE_WALKS_TEST = ("walking_27", "walking_28", "35_30")
ONSETS13 = (30, 90, 240)   # loco13's erasure onsets after the seam


def cases13(channels, split="validation"):
    """loco13's larger regime set (module doc, ``--set loco13``)."""
    legs = np.isin(withhlm.group_index(list(channels)), withhlm.LEG_GROUPS)
    takes = splits.TEST if split == "test" else splits.VALIDATION
    for t, act, x, obs in cases(channels, split):
        if act != "splice":
            yield t, act, x, obs
    for w in [t for t in takes if splits.ACTIVITY[t] in ("walk", "turn", "run")]:
        for t in [t for t in takes if splits.ACTIVITY[t] == "nonloco"]:
            x, n1 = splice(w, t)
            for on in ONSETS13:
                obs = np.ones(x.shape, bool)
                obs[n1 + on:, ~legs] = False
                yield f"{w}+{t}@{on}", "splice", x, obs


def cases(channels, split="validation"):
    legs = np.isin(withhlm.group_index(list(channels)), withhlm.LEG_GROUPS)
    takes = splits.TEST if split == "test" else splits.VALIDATION
    for t in takes:
        x = np.array(protocols.load_take(t).frames)
        obs = np.ones(x.shape, bool)
        obs[len(x) // 2:, ~legs] = False
        yield t, splits.ACTIVITY[t], x, obs
    for w in SPLICE_WALKS_TEST if split == "test" else SPLICE_WALKS:
        for t in [t for t in takes if splits.ACTIVITY[t] == "nonloco"]:
            x, n1 = splice(w, t)   # (the stress bench's splice)
            obs = np.ones(x.shape, bool)
            obs[n1 + 30:, ~legs] = False
            yield f"{w}+{t}", "splice", x, obs


def run(m, x, obs, blend=False):
    st = m.default.stream() if blend else m.stream()
    out = np.empty_like(x)
    for t in range(len(x)):
        out[t] = st.step(np.where(obs[t], x[t], np.nan), obs[t]).frame
    return out, st


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("models", nargs="+")
    ap.add_argument("--split", choices=("validation", "test"), default="validation")
    ap.add_argument("--set", choices=("loco12", "loco13"), default="loco12")
    ap.add_argument("--ll", action="append", default=[], help="D,TAU[,legs]: each model also with long_ll (D, TAU) [its legs-only baseline]")
    ap.add_argument("--json")
    a = ap.parse_args()
    import blend.methods  # noqa: F401  (loaders)

    models = [modelfile.load_model(p) for p in a.models]
    names = [Path(p).stem for p in a.models]
    for p in list(a.models):
        for spec in a.ll:
            d, tau = (float(v) for v in spec.split(",")[:2])
            m = modelfile.load_model(p)
            m.set_long_ll(d, tau)
            m.set_long_ll_legs(spec.split(",")[2:] == ["legs"])   # (else the whole-body baseline, even if the file's is the legs')
            models.append(m)
            names.append(f"{Path(p).stem}_ll{spec.replace(',', '_')}")
    ang = np.array([is_angle(c) for c in models[0].channels])
    rows = []
    t0 = time.time()
    for label, act, x, obs in (cases13 if a.set == "loco13" else cases)(models[0].channels, a.split):
        msk = ~obs & ang[None]
        e = {}
        for name, m in zip(names, models, strict=True):
            out, st = run(m, x, obs)
            e[name] = float(np.mean(wrap(out - x)[msk] ** 2))
            e[name + ":lwin"] = st.n_lwin
            e[name + ":llrev"] = st.n_llrev
        out, _ = run(models[0], x, obs, blend=True)
        e["blend"] = float(np.mean(wrap(out - x)[msk] ** 2))
        hold = np.array(x)
        for t in range(1, len(x)):
            hold[t] = np.where(obs[t], x[t], hold[t - 1])
        e["hold"] = float(np.mean(wrap(hold - x)[msk] ** 2))
        e["n"] = int(msk.sum())
        rows.append({"case": label, "act": act, **e})
        print(f"{label:34s} {act:8s} " + " ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in e.items()),
              flush=True)
    print(f"{len(rows)} cases, {time.time() - t0:.0f} s")
    sel = [r for r in rows if r["act"] != "walk"]
    pooled = {k: sum(r[k] * r["n"] for r in sel) / sum(r["n"] for r in sel) for k in names + ["blend", "hold"]}
    print("pooled MSE over the non-walk cases:", {k: round(v, 4) for k, v in pooled.items()})
    for k in names[1:]:
        worst = max(sel, key=lambda r: r[k] / r[names[0]])
        print(f"{k} / {names[0]}: max {worst[k] / worst[names[0]]:.4f} ({worst['case']}), "
              f"cases > 1.01: {sum(r[k] > 1.01 * r[names[0]] for r in sel)}")
        wk = [r for r in rows if r["act"] == "walk"]
        if wk:
            ww = max(wk, key=lambda r: r[k] / r[names[0]])
            print(f"  walks: max {ww[k] / ww[names[0]]:.4f} ({ww['case']}); revokes on non-walk cases "
                  f"{sum(r[k + ':llrev'] > 0 for r in sel)} of {len(sel)}, on walks {sum(r[k + ':llrev'] > 0 for r in wk)} of {len(wk)}")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=0))
    return 0


if __name__ == "__main__":
    sys.exit(main())
