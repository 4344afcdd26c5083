"""Fit and check ``default``'s per-channel std calibration (blend/calib.py) on VALIDATION only.

fit:    run a ``default`` model file (its calibration set to 1) over VALIDATION with the cases
        bench/default_hlm_tune.py builds (gaps bursts seeds 100-102, pan2009's pattern on the
        walks), keep truth, fill, std, channel and frames since onset of every erased value;
        choose the shrinkage N0 (channel -> group) and N1 (group x time bin -> 1) by leaving one
        VALIDATION take out at a time; fit on all of VALIDATION; write the factors into
        blend/withhlm.json ("calib", --write) and a calibrated copy of the model (--out).

    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python bench/default_calib.py fit \
        --model bench/out/mq_dh1_gaps.npz --cache bench/out/cal_val.npz --out bench/out/cal_gaps.npz --write

report: within 1 and 2 std and Gaussian NLL (mocap.metrics' STD_FLOOR and NLL) per activity, per
        group, and the worst channels by |within 2 std - 0.95| from ``lacuna eval --fills`` dirs
        (angles scored by the protocol; fills are compared between the dirs: they must be equal).

    .venv/bin/python bench/default_calib.py report before=DIR after=DIR
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from blend import calib, withhlm  # noqa: E402
from lacuna import modelfile  # noqa: E402
from mocap import splits  # noqa: E402
from mocap.metrics import STD_FLOOR, gaussian_nll  # noqa: E402
from mocap.representation import is_angle  # noqa: E402
from mocap.rootrot import wrap180 as wrap  # noqa: E402

N0S = (0.0, 300.0, 3000.0, 30000.0, math.inf)
N1S = (math.inf, 0.0, 1000.0)
EACHS = (None, 0.92, 0.94)
N2S = (math.inf,)
ACTS = ("walk", "turn", "run", "nonloco")
MIN_CELL = 100   # held-out values a channel / group x bin needs to count in the criterion


def collect(model: withhlm.WithHLMModel) -> dict[str, np.ndarray]:
    from bench.default_hlm_tune import cases

    rows: dict[str, list] = {k: [] for k in ("err", "std", "c", "k", "take", "act", "pat")}
    takes = sorted(splits.VALIDATION)
    t0 = time.time()
    for pat, c in cases():
        st = model.stream()
        x, obs = c.truth, c.observed
        for t in range(x.shape[0]):
            f = st.step(x[t], obs[t])
            j = np.flatnonzero(~obs[t])
            if not len(j):
                continue
            e = f.frame[j] - x[t, j]
            rows["err"].append(np.where(model.ang[j], wrap(e), e))
            rows["std"].append(f.std[j])
            rows["c"].append(j)
            rows["k"].append(st.k[j].copy())
            rows["take"].append(np.full(len(j), takes.index(c.test)))
            rows["act"].append(np.full(len(j), ACTS.index(splits.ACTIVITY[c.test])))
            rows["pat"].append(np.full(len(j), pat == "pan2009"))
        print(f"  {pat} {c.test}: {x.shape[0]} frames, {time.time() - t0:.0f} s", flush=True)
    return {k: np.concatenate(v) for k, v in rows.items()}


def _z(data):
    """|error| / std; 0 where the error is 0 to rounding (a channel held still: no evidence)."""
    a = np.abs(data["err"])
    return np.where(a < 1e-6, 0.0, a / np.maximum(data["std"], 1e-9))


def criterion(w2: np.ndarray, keys: list[np.ndarray]) -> float:
    """Mean over cells (each key array's values with >= MIN_CELL values) of |within 2 std - 0.95|,
    averaged over the kinds of cell (channels, group x time bin)."""
    out = []
    for key in keys:
        u, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
        share = np.bincount(inv, w2) / cnt
        out.append(float(np.mean(np.abs(share[cnt >= MIN_CELL] - calib.Q))))
    return float(np.mean(out))


def choose(data, group, n_ch, n_tb, n0s=N0S, n1s=N1S, eachs=EACHS, n2s=N2S):
    """(N0, N1, each) by leaving one VALIDATION take out at a time (module doc): the criterion is
    the mean |within 2 std - 0.95| of the held-out values over channel x activity cells, over
    group x time-bin cells and over channel x time-bin cells (blend/calib.py's module doc), angles
    only."""
    z, c, tb, act = _z(data), data["c"], withhlm.t_bin(data["k"]), data["act"]
    g = group[c]
    ang = data["ang"]
    keys = [(c * 10 + act)[ang], (g * 100 + tb)[ang], (c * 100 + tb)[ang]]
    w2 = (z <= 2)[ang]
    base = criterion(w2, keys)
    print(f"  uncalibrated (F = 1): mean |w2 - 0.95| {base:.4f}  by activity "
          + " ".join(f"{np.mean(w2[act[ang] == a]):.3f}" for a in range(4)))
    res = []
    for each, n2 in [(e, n) for e in eachs for n in n2s]:
        for n1 in n1s:
            for n0 in n0s:
                zz = np.empty_like(z)
                for t in np.unique(data["take"]):
                    out = data["take"] == t
                    F = calib.fit(z[~out], c[~out], g[~out], tb[~out], n_ch, n_tb, n0, n1, act[~out], each, n2)
                    zz[out] = z[out] / F[c[out], tb[out]]
                w2 = (zz <= 2)[ang]
                crit = criterion(w2, keys)
                acts = [float(np.mean(w2[act[ang] == a])) for a in range(4)]
                res.append((crit, n0, n1, -1.0 if each is None else each, n2))
                print(f"  each {each} N2 {n2:>6g} N0 {n0:>7g} N1 {n1:>6g}: held-out mean |w2 - 0.95| {crit:.4f}  by activity "
                      + " ".join(f"{v:.3f}" for v in acts), flush=True)
    crit, n0, n1, each, n2 = min(res)
    return crit, n0, n1, None if each < 0 else each, n2


def cmd_fit(a) -> int:
    import blend.methods  # noqa: F401  (loaders)

    m = modelfile.load_model(a.model)
    n_ch, n_tb = m.n_channels, len(withhlm.T_EDGES) + 1
    m0 = withhlm.WithHLMModel(m.default, m.hlm, m.W, m.S, m.meta, m.tau)   # its calibration: 1
    if a.cache and Path(a.cache).exists():
        data = dict(np.load(a.cache))
    else:
        data = collect(m0)
        if a.cache:
            np.savez(a.cache, **data)
    data["ang"] = np.asarray(m0.ang)[data["c"]] & ~np.isin(m0.group[data["c"]], [withhlm.ROOT_POS])
    grid = (a.n0 or N0S, a.n1 or N1S, [None if e < 0 else e for e in a.each] if a.each else EACHS, a.n2 or N2S)
    crit, n0, n1, each, n2 = choose(data, m0.group, n_ch, n_tb, *grid)
    print(f"chosen N0 {n0:g}, N1 {n1:g}, each {each}, N2 {n2:g} (held-out criterion {crit:.4f})")
    tb = withhlm.t_bin(data["k"])
    F = calib.fit(_z(data), data["c"], m0.group[data["c"]], tb, n_ch, n_tb, n0, n1, data["act"], each, n2)
    for i in np.argsort(-np.abs(np.log(F)).max(1))[:12]:
        print(f"  {m0.channels[i]:14s} " + " ".join(f"{v:5.2f}" for v in F[i]))
    if a.out:
        withhlm.WithHLMModel(m.default, m.hlm, m.W, m.S, m.meta, m.tau, F).save(a.out)
        print(f"wrote {a.out}")
    if a.write:
        d = json.loads(withhlm.SHIPPED.read_text())
        d["calib"] = calib.to_json(F, m0.channels, m0.group, withhlm.GROUP_NAMES, {
            "fitted_on": "VALIDATION: gaps bursts seeds 100,101,102 + pan2009 pattern on its walks",
            "model": Path(a.model).name, "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            "N0": n0 if math.isfinite(n0) else "inf", "N1": n1 if math.isfinite(n1) else "inf", "each": each, "N2": n2 if math.isfinite(n2) else "inf",
            "loto_criterion": round(crit, 4),
            "chosen_by": "leave one VALIDATION take out over the N0 x N1 x N2 x each grid of bench/default_calib.py (bench/notebook/calib-4.md)"})
        withhlm.SHIPPED.write_text(json.dumps(d, indent=1) + "\n")
        print(f"wrote {withhlm.SHIPPED}")
    return 0


# ---- report from lacuna eval --fills dirs -------------------------------------------------------
def load_fills(d: str):
    from blend.model import GROUP_NAMES, group_of

    rows: dict[str, list] = {k: [] for k in ("err", "std", "c", "act", "fill", "k")}
    channels = None
    for p in sorted(Path(d).glob("*.npz")):
        z = np.load(p)
        channels = [str(c) for c in z["channels"]]
        sc = z["erased"] & (z["scored"][None, :] if "scored" in z else np.array([is_angle(c) for c in channels])[None, :])
        t, j = np.nonzero(sc)
        e = wrap(z["fill"][t, j] - z["truth"][t, j])
        take = p.stem.split("-")[0]
        take = next((n for n in splits.ACTIVITY if p.stem.startswith(n)), take)
        rows["err"].append(e)
        rows["std"].append(z["std"][t, j])
        rows["c"].append(j)
        rows["act"].append(np.full(len(j), ACTS.index(splits.ACTIVITY[take])))
        rows["fill"].append(z["fill"][t, j])
        er = z["erased"]
        k = np.zeros(er.shape, np.int64)   # frames since onset: 1 on a gap's first erased frame
        for r in range(er.shape[0]):
            k[r] = np.where(er[r], (k[r - 1] if r else 0) + 1, 0)
        rows["k"].append(k[t, j])
    out = {k: np.concatenate(v) for k, v in rows.items()}
    assert channels is not None, f"no fills in {d}"
    out["g"] = np.array([group_of(c) for c in channels])[out["c"]]
    return out, channels, GROUP_NAMES


def _s(err, std):
    s = np.maximum(std, STD_FLOOR)
    a = np.abs(err)
    return float(np.mean(a <= s)), float(np.mean(a <= 2 * s)), float(np.mean(gaussian_nll(err, std)))


def cmd_report(a) -> int:
    runs = dict(x.split("=", 1) for x in a.runs)
    loaded = {k: load_fills(v) for k, v in runs.items()}
    names = list(runs)
    ref = loaded[names[0]][0]
    for k in names[1:]:
        same = len(ref["fill"]) == len(loaded[k][0]["fill"]) and np.array_equal(ref["fill"], loaded[k][0]["fill"])
        print(f"fills {names[0]} vs {k}: {'bit-equal' if same else 'DIFFER'} ({len(ref['fill'])} values)")
    _, channels, gnames = loaded[names[0]]
    hdr = " / ".join(names)
    print(f"\n| cell | n | within 1 std ({hdr}) | within 2 std ({hdr}) | NLL ({hdr}) |\n|---|---|---|---|---|")

    def row(label, sel_fn):
        cells = []
        n = 0
        for k in names:
            d = loaded[k][0]
            m = sel_fn(d)
            n = int(m.sum())
            cells.append(_s(d["err"][m], d["std"][m]) if n else (float("nan"),) * 3)
        print(f"| {label} | {n} | " + " | ".join(" / ".join(f"{c[i]:.3f}" for c in cells) for i in range(3)) + " |")

    row("all", lambda d: np.ones(len(d["err"]), bool))
    for i, act in enumerate(ACTS):
        row(act, lambda d, i=i: d["act"] == i)
    for g, gn in enumerate(gnames):
        row(f"group {gn}", lambda d, g=g: d["g"] == g)
    tb0 = withhlm.t_bin(ref["k"])
    edges = ["1", "2-6", "7-12", "13-30", "31-60", "61-120", "121-240", ">240"]
    print(f"\nwithin 2 std by group x frames since onset ({hdr}; cells with >= {MIN_CELL} values):")
    print("| group | " + " | ".join(edges) + " |\n|---|" + "---|" * len(edges))
    for g, gn in enumerate(gnames):
        cells = []
        for t in range(len(edges)):
            m = (ref["g"] == g) & (tb0 == t)
            cells.append(" / ".join(f"{_s(loaded[k][0]['err'][m], loaded[k][0]['std'][m])[1]:.3f}" for k in names)
                         if m.sum() >= MIN_CELL else "-")
        if any(x != "-" for x in cells):
            print(f"| {gn} | " + " | ".join(cells) + " |")
    d0 = loaded[names[0]][0]
    still = [c for c in np.unique(d0["c"]) if np.abs(d0["err"][d0["c"] == c]).max() < 1e-6]
    print(f"\n{len(still)} channels never off (error 0 to rounding: {', '.join(channels[c] for c in still)}) "
          "are left out below: within 2 std is 1 whatever the band")
    for who in names:
        dw = loaded[who][0]
        dev = []
        for c in np.unique(dw["c"]):
            m = dw["c"] == c
            if m.sum() >= MIN_CELL and c not in still:
                dev.append((abs(_s(dw["err"][m], dw["std"][m])[1] - 0.95), c))
        print(f"\nworst {a.worst} channels by |within 2 std - 0.95| in {who}, and in each run:")
        print(f"| channel | n | within 2 std ({hdr}) | NLL ({hdr}) |\n|---|---|---|---|")
        _worst(loaded, names, channels, sorted(dev, reverse=True)[:a.worst])
    for k in names:
        d = loaded[k][0]
        w2s = np.array([_s(d["err"][m], d["std"][m])[1] for c in np.unique(d["c"])
                        if (m := d["c"] == c).sum() >= MIN_CELL and c not in still])
        dv = np.abs(w2s - 0.95)
        print(f"{k}: channels {len(w2s)}, mean |w2 - 0.95| {dv.mean():.4f}, max {dv.max():.4f}, "
              f"outside 0.90-0.98: {int(np.sum((w2s < 0.90) | (w2s > 0.98)))}")
    return 0


def _worst(loaded, names, channels, dev):
    d0 = loaded[names[0]][0]
    for _, c in dev:
        cells = [_s(loaded[k][0]["err"][loaded[k][0]["c"] == c], loaded[k][0]["std"][loaded[k][0]["c"] == c]) for k in names]
        print(f"| {channels[c]} | {int((d0['c'] == c).sum())} | " + " / ".join(f"{x[1]:.3f}" for x in cells)
              + " | " + " / ".join(f"{x[2]:.2f}" for x in cells) + " |")


def cmd_apply(a) -> int:
    """A copy of a default model file with blend/withhlm.json's factors (by channel name)."""
    import blend.methods  # noqa: F401  (loaders)

    m = modelfile.load_model(a.model)
    d = json.loads(withhlm.SHIPPED.read_text()).get("calib")
    F = calib.from_json(d, m.channels, m.group, withhlm.GROUP_NAMES, len(withhlm.T_EDGES) + 1)
    withhlm.WithHLMModel(m.default, m.hlm, m.W, m.S, m.meta, m.tau, F).save(a.out)
    print(f"wrote {a.out} (factors {F.min():.2f}-{F.max():.2f})")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    f = sub.add_parser("fit")
    f.add_argument("--model", required=True, help="a default model file trained on splits.TRAIN")
    f.add_argument("--cache", help="npz of collected VALIDATION values (read if it exists, else written)")
    f.add_argument("--out", help="write a copy of the model with the fitted calibration")
    f.add_argument("--write", action="store_true", help="write the factors into blend/withhlm.json")
    f.add_argument("--n0", type=float, nargs="+", help=f"N0 values to try (default {N0S})")
    f.add_argument("--n1", type=float, nargs="+", help=f"N1 values to try (default {N1S})")
    f.add_argument("--n2", type=float, nargs="+", help=f"N2 values to try (default {N2S})")
    f.add_argument("--each", type=float, nargs="+", help=f"each values to try, -1 for none (default {EACHS})")
    r = sub.add_parser("report")
    r.add_argument("runs", nargs="+", help="NAME=DIR of lacuna eval --fills output")
    r.add_argument("--worst", type=int, default=10)
    p = sub.add_parser("apply")
    p.add_argument("--model", required=True)
    p.add_argument("--out", required=True)
    a = ap.parse_args()
    return {"fit": cmd_fit, "report": cmd_report, "apply": cmd_apply}[a.cmd](a)


if __name__ == "__main__":
    sys.exit(main())
