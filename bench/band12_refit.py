"""band-12 round 2 (bench/notebook/band-12.md): the band's rate (blend/withhlm.py "Rate") with the std
scale S refitted by S's own rule on the model's final band, on S's own fitting collection (VALIDATION:
the gaps protocol's bursts seeds 100-102 and pan2009's pattern, bench/default_hlm_tune.py's cases).

For each --rate-a: the model's fills and stds with the shipped smoothing and that exponent; over each
(group, time bin) cell's erased angle values z = |error| / std, M = max(q95(z), q92(z) of each activity
with >= 100 values) / 2 (default_hlm_tune.fit's rule for S; cells with < 100 values: 1); S' = S M.
Writes the model with S' (and the rate's reference, rate_a set) to --out-dir/refit_a{A}.npz and the
factors to --out-dir/refit_a{A}.json, to be scored by bench/default_smooth.py --model on other seeds.

    OPENBLAS_NUM_THREADS=1 nice -n 19 .venv/bin/python bench/band12_refit.py --model /tmp/band12_train.npz \
        --rate-a 0 0.5 1 --out-dir /tmp/band12
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from blend import withhlm  # noqa: E402
from lacuna.modelfile import load_model  # noqa: E402
from mocap import protocols, splits  # noqa: E402
from mocap.rootrot import wrap180 as wrap  # noqa: E402

SEEDS = (100, 101, 102)
ACTS = ("walk", "turn", "run", "nonloco")
Q, EACH, MIN_VALUES = 0.95, 0.92, 100   # default_hlm_tune.fit's (COVER_EACH, MIN_VALUES)


def cases():
    for s in SEEDS:
        yield from protocols.Gaps(seed=s, split="validation").cases()
    yield from protocols.Pan2009(split="validation").cases()


def since_onset(observed: np.ndarray) -> np.ndarray:
    k = np.zeros(observed.shape, np.int64)
    for t in range(len(observed)):
        k[t] = np.where(observed[t], 0, (k[t - 1] if t else 0) + 1)
    return k


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", required=True)
    ap.add_argument("--rate-a", type=float, nargs="+", default=[0.0, 0.5, 1.0])
    ap.add_argument("--out-dir", default="/tmp/band12")
    a = ap.parse_args()
    model = load_model(a.model)
    if model.rate_ref is None:
        model.set_rate_ref(withhlm.rate_ref(protocols.Gaps().training_set().sequences, list(model.channels)))
    S0 = model.S.copy()
    cs = list(cases())
    G, TB = S0.shape
    for ra in a.rate_a:
        model.set_scale(S0)
        model.set_smooth(**{**withhlm.SMOOTH, "rate_a": ra})
        zs, gs, ts, acts = [], [], [], []
        t0 = time.perf_counter()
        for c in cs:
            given = np.where(c.observed, c.truth, np.nan)
            fill, std = model.fill_offline(given, c.observed)
            sel = ~c.observed & model.ang[None, :] & (std > 0)
            err = np.abs(wrap(fill - c.truth))[sel]
            zs.append(err / std[sel])
            gs.append(np.broadcast_to(model.group[None, :], sel.shape)[sel])
            ts.append(withhlm.t_bin(since_onset(c.observed))[sel])
            acts.append(np.full(int(sel.sum()), ACTS.index(splits.ACTIVITY[c.test])))
        z, g, tb, act = (np.concatenate(x) for x in (zs, gs, ts, acts))
        M = np.ones((G, TB))
        for gi in range(G):
            for t in range(TB):
                cell = (g == gi) & (tb == t)
                if cell.sum() < MIN_VALUES:
                    continue
                qs = [np.quantile(z[cell], Q)] + [np.quantile(z[m], EACH) for k in range(len(ACTS))
                                                  if (m := cell & (act == k)).sum() >= MIN_VALUES]
                M[gi, t] = float(max(qs) / 2.0)
        model.set_scale(S0 * M)
        out = Path(a.out_dir)
        out.mkdir(parents=True, exist_ok=True)
        model.save(str(out / f"refit_a{ra:g}.npz"))
        within = {ACTS[k]: float((z[act == k] <= 2.0).mean()) for k in range(len(ACTS)) if (act == k).any()}
        (out / f"refit_a{ra:g}.json").write_text(json.dumps({"rate_a": ra, "M": M.round(4).tolist(),
                                                             "within_2std_before_refit": within}, indent=1) + "\n")
        print(f"a {ra:g}: {len(cs)} cases in {time.perf_counter() - t0:.0f} s; within 2 std before the refit "
              + " ".join(f"{k} {v:.4f}" for k, v in within.items()) + "; M median "
              + f"{np.median(M):.3f}, min {M.min():.3f}, max {M.max():.3f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
