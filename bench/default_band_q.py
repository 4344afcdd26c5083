"""band-13 (bench/notebook/band-13.md): fit band_q (blend/withhlm.py "Band q") and its rate gate on
VALIDATION gaps seeds 100-102 (neither the rule's seeds 0-2 nor 3-4), with the model's band_q off.

Over erased angle values z = |error| / std, with their stream's q bin at that frame and the stream's
rate R (blend.withhlm_fast.stream_rate, before that frame's update, as q_band reads it):
band_q per (group, q bin) for bins 0, 1: M = max(q95(z) pooled, q92(z) of each activity with >= 100
values) / 2 (default_hlm_tune.fit's rule for S); q0 takes q1's value where q0 has < 100 values; 1 in
cells with < 100 values; groups other / root-pos and bins q2, q3: 1.  The gate: r0 = the walks' 90%
quantile of R, r1 = the run's 10% quantile; if r1 <= r0, both their mean.  Writes --out (JSON: M, gate,
R's quantiles per activity, the within-2-std share per (activity, q bin) before the fit).

    OPENBLAS_NUM_THREADS=1 nice -n 19 .venv/bin/python bench/default_band_q.py --model /tmp/band13_train.npz \
        --out bench/results/band13_fit.json

``--write JSON`` writes that fit into blend/withhlm.json ("band_q": M, gate, where fitted and chosen),
which ``train_model`` then applies (blend.withhlm.shipped_band_q).  ``--check JSON`` instead compares the compiled and the numpy mixing with that fit on one VALIDATION take
(fills equal to band_q off, stds equal to 1e-9 between the two paths) and prints the largest differences.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from blend import withhlm  # noqa: E402
from blend.withhlm_fast import rate_band, stream_rate  # noqa: E402
from lacuna.modelfile import load_model  # noqa: E402
from mocap import protocols, splits  # noqa: E402
from mocap.rootrot import wrap180 as wrap  # noqa: E402

SEEDS = (100, 101, 102)
ACTS = ("walk", "turn", "run", "nonloco")
Q, EACH, MIN_VALUES = 0.95, 0.92, 100   # default_hlm_tune.fit's (COVER_EACH, MIN_VALUES)
FIT_BINS = (0, 1)
NO_GROUPS = ("other", "root-pos")


def collect(model, cases):
    """Per erased angle value: z, group, q bin, activity index, the stream's rate R (-1: none)."""
    zs, gs, qs, acts, rs = [], [], [], [], []
    rpar = np.array([math.exp(-1.0 / withhlm.RATE_TAU), 0.0, 1.0, 1.0])   # a = 0: rate_band only updates the sums
    C = model.n_channels
    for c in cases:
        st = model.stream()
        rst, buf, dummy = np.zeros((4, C)), np.zeros(C), np.zeros(C)
        n = len(c.truth)
        fill, std = np.empty((n, C)), np.empty((n, C))
        qb, R = np.empty(n, np.int64), np.empty(n)
        given = np.where(c.observed, c.truth, np.nan)
        for t in range(n):
            R[t] = stream_rate(model.ang, model._ref, rst, buf)
            f = st.step(given[t], c.observed[t])
            fill[t], std[t] = f.frame, f.std
            qb[t] = withhlm.q_bin(st.logq)
            o = np.ascontiguousarray(c.observed[t])
            rate_band(np.where(o, given[t], 0.0), o, model.ang, dummy, rpar, model._ref, rst)
        sel = ~c.observed & model.ang[None, :] & (std > 0)
        err = np.abs(wrap(fill - c.truth))[sel]
        zs.append(err / std[sel])
        gs.append(np.broadcast_to(model.group[None, :], sel.shape)[sel])
        qs.append(np.broadcast_to(qb[:, None], sel.shape)[sel])
        rs.append(np.broadcast_to(R[:, None], sel.shape)[sel])
        acts.append(np.full(int(sel.sum()), ACTS.index(splits.ACTIVITY[c.test])))
    return tuple(np.concatenate(x) for x in (zs, gs, qs, acts, rs))


def fit(z, g, qb, act, R):
    G, QB = len(withhlm.GROUP_NAMES), len(withhlm.Q_EDGES) + 1
    M = np.ones((G, QB))
    for gi, name in enumerate(withhlm.GROUP_NAMES):
        if name in NO_GROUPS:
            continue
        for q in FIT_BINS:
            cell = (g == gi) & (qb == q)
            if cell.sum() < MIN_VALUES:
                continue
            qs = [np.quantile(z[cell], Q)] + [np.quantile(z[m], EACH) for k in range(len(ACTS))
                                              if (m := cell & (act == k)).sum() >= MIN_VALUES]
            M[gi, q] = float(max(qs) / 2.0)
        if ((g == gi) & (qb == 0)).sum() < MIN_VALUES:
            M[gi, 0] = M[gi, 1]
    has = R >= 0
    r0 = float(np.quantile(R[has & (act == ACTS.index("walk"))], 0.9))
    r1 = float(np.quantile(R[has & (act == ACTS.index("run"))], 0.1))
    if r1 <= r0:
        r0 = r1 = (r0 + r1) / 2
    return M, [r0, r1]


def check(model, fitted: dict) -> int:
    from lacuna import jit

    c = next(c for c in protocols.Gaps(seed=0, split="validation").cases() if splits.ACTIVITY[c.test] == "walk")
    given = np.where(c.observed, c.truth, np.nan)
    model.set_band_q(np.ones_like(np.array(fitted["M"])))
    f0, s0 = model.fill_offline(given, c.observed)
    for gate in (fitted["gate"], None):
        model.set_band_q(np.array(fitted["M"]), gate)
        model.compiled = True
        fa, sa = model.fill_offline(given, c.observed)
        model.compiled = False
        fb, sb = model.fill_offline(given, c.observed)
        model.compiled = jit.enabled()
        miss = ~c.observed & (s0 > 1e-9)
        print(f"{c.test} gate {gate}: compiled fills equal to off {np.array_equal(fa, f0)}, numpy's within "
              f"{np.abs(fb - f0).max():.1e}; "
              f"max |std compiled - numpy| {np.abs(sa - sb).max():.2e}; std / off: min {np.min(sa[miss] / s0[miss]):.3f} "
              f"median {np.median(sa[miss] / s0[miss]):.3f}")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--model")
    ap.add_argument("--out", default="bench/results/band13_fit.json")
    ap.add_argument("--write", help="a fit's JSON: write it into blend/withhlm.json as the shipped band_q")
    ap.add_argument("--check", help="a fit's JSON: compiled vs numpy mixing with it (see the module doc)")
    a = ap.parse_args()
    if a.write:
        fitted = json.loads(Path(a.write).read_text())
        d = json.loads(withhlm.SHIPPED.read_text())
        d["band_q"] = {"M": fitted["M"], "gate": fitted["gate"], "fitted_on": fitted["fitted_on"],
                       "chosen_on": "VALIDATION gaps seeds 0-2 and 3-4 (rule), TEST 0-4 after the choice: "
                                    "bench/notebook/band-13.md"}
        withhlm.SHIPPED.write_text(json.dumps(d, indent=1) + "\n")
        print(f"wrote {withhlm.SHIPPED}")
        return 0
    if not a.model:
        ap.error("--model is needed to fit or check")
    model = load_model(a.model)
    if model.rate_ref is None:
        model.set_rate_ref(withhlm.rate_ref(protocols.Gaps().training_set().sequences, list(model.channels)))
    model.set_smooth(**withhlm.SMOOTH)
    if a.check:
        return check(model, json.loads(Path(a.check).read_text()))
    model.set_band_q(np.ones((len(withhlm.GROUP_NAMES), len(withhlm.Q_EDGES) + 1)))
    t0 = time.perf_counter()
    cases = [c for s in SEEDS for c in protocols.Gaps(seed=s, split="validation").cases()]
    z, g, qb, act, R = collect(model, cases)
    M, gate = fit(z, g, qb, act, R)
    rq = {ACTS[k]: [float(x) for x in np.quantile(R[(act == k) & (R >= 0)], [0.1, 0.5, 0.9])]
          for k in range(len(ACTS)) if ((act == k) & (R >= 0)).any()}
    within = {f"{ACTS[k]}/q{q}": [float((z[m] <= 2).mean()), int(m.sum())]
              for k in range(len(ACTS)) for q in range(M.shape[1]) if (m := (act == k) & (qb == q)).any()}
    out = {"fitted_on": "VALIDATION gaps seeds " + ",".join(map(str, SEEDS)), "model": a.model,
           "M": M.round(4).tolist(), "gate": [round(x, 4) for x in gate], "rate_q10_median_q90": rq,
           "within_2std_by_q_before": within, "seconds": round(time.perf_counter() - t0, 1)}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps({k: out[k] for k in ("M", "gate", "rate_q10_median_q90")}, indent=None))
    return 0


if __name__ == "__main__":
    sys.exit(main())
