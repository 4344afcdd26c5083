"""loco-12's regime check (bench/notebook/loco-12.md, rule item 7): the leg gate (blend/withhlm.py,
"Long erasures") where it acts, on VALIDATION takes only: pan2009's pattern (every channel but the legs
erased from half way) on each VALIDATION take, and the stress bench's splices (bench/default_stress.py:
a walk's first 5 s, then a non-locomotion take) erased but the legs from 30 frames after the seam.
MSE (deg^2) over the erased angles of ``default`` per model file given, its blend alone and hold.
``--split test`` (only after a choice, reported, never used to choose): the same on TEST's takes, the
splices' walks TEST's walking_27, walking_28 and 35_30 (fixed before the run, as VALIDATION's two
walking_ takes and one of subject 35).

    OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/loco12_regime.py OFF.npz ON.npz [--split test] [--json OUT]
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
    ap.add_argument("--json")
    a = ap.parse_args()
    import blend.methods  # noqa: F401  (loaders)

    models = [modelfile.load_model(p) for p in a.models]
    ang = np.array([is_angle(c) for c in models[0].channels])
    rows = []
    t0 = time.time()
    for label, act, x, obs in cases(models[0].channels, a.split):
        msk = ~obs & ang[None]
        e = {}
        for p, m in zip(a.models, models, strict=True):
            out, st = run(m, x, obs)
            e[Path(p).stem] = float(np.mean(wrap(out - x)[msk] ** 2))
            e[Path(p).stem + ":lwin"] = st.n_lwin
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
    names = [Path(p).stem for p in a.models]
    print(f"{len(rows)} cases, {time.time() - t0:.0f} s")
    sel = [r for r in rows if r["act"] != "walk"]
    pooled = {k: sum(r[k] * r["n"] for r in sel) / sum(r["n"] for r in sel) for k in names + ["blend", "hold"]}
    print("pooled MSE over the non-walk cases:", {k: round(v, 4) for k, v in pooled.items()})
    for k in names[1:]:
        worst = max(sel, key=lambda r: r[k] / r[names[0]])
        print(f"{k} / {names[0]}: max {worst[k] / worst[names[0]]:.4f} ({worst['case']}), "
              f"cases > 1.01: {sum(r[k] > 1.01 * r[names[0]] for r in sel)}")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=0))
    return 0


if __name__ == "__main__":
    sys.exit(main())
