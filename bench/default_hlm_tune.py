"""Fit ``default-hlm``'s stacking weights W and std scale S on the VALIDATION split only.

The experts (``default`` and ``hlm``) are trained on splits.TRAIN (the HLM on its locomotion
takes), or read from --default/--hlm model files.  Both run over every VALIDATION take with the
gaps protocol's bursts (seeds 100-102; the protocol's own are 0-4) and, on the validation walks,
pan2009's pattern (everything but the legs erased from half way); every missing value's two fills,
stds, frames since onset and the stream's shadow evidence q are collected, then W is fitted per
(group, time since onset, q) cell in two folds by take (the smaller weight kept) and S per
(group, time since onset) so that 2 std hold 95%.  Writes blend/withhlm.json (--write) and prints
the validation RMS per activity of default, hlm and the blend on the same values.

    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python bench/default_hlm_tune.py \
        --default bench/out/hx_default_gaps.npz --hlm bench/out/hx_hlm_gaps.npz --write
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from blend import withhlm  # noqa: E402
from lacuna import modelfile  # noqa: E402
from mocap import protocols, splits  # noqa: E402
from mocap.rootrot import wrap180 as wrap  # noqa: E402

SEEDS = (100, 101, 102)
TAUS = (0.0, 15.0, 30.0, 60.0, 120.0)   # the HLM's anchoring decay, frames (0: none)


def cases():
    for s in SEEDS:
        for c in protocols.Gaps(seed=s, split="validation").cases():
            yield f"gaps{s}", c
    for c in protocols.Pan2009(split="validation").cases():
        yield "pan2009", c


def collect(model: withhlm.WithHLMModel) -> dict[str, np.ndarray]:
    rows: dict[str, list] = {k: [] for k in ("y", "D", "H", "o", "sD", "sH", "g", "k", "logq", "ang", "take", "act", "pat")}
    takes = sorted(splits.VALIDATION)
    t0 = time.time()
    for pat, c in cases():
        st = model.stream()
        st.collect = True
        x, obs = c.truth, c.observed
        for t in range(x.shape[0]):
            st.step(x[t], obs[t])
            comp = st.comp
            if comp is None:
                continue
            j = comp["idx"]
            n = len(j)
            rows["y"].append(x[t, j])
            for key in ("D", "H", "o", "sD", "sH", "k", "logq"):
                rows[key].append(comp[key])
            rows["g"].append(model.group[j])
            rows["ang"].append(model.ang[j])
            rows["take"].append(np.full(n, takes.index(c.test)))
            rows["act"].append(np.full(n, ("walk", "turn", "run", "nonloco").index(splits.ACTIVITY[c.test])))
            rows["pat"].append(np.full(n, pat == "pan2009"))
        print(f"  {pat} {c.test}: {x.shape[0]} frames, q {np.exp(st.logq):.2f}, {time.time() - t0:.0f} s", flush=True)
    return {k: np.concatenate(v) for k, v in rows.items()}


def parts(data: dict[str, np.ndarray], tau: float):
    """Bins, residual of default (truth - D) and the HLM's anchored difference (H' - D)."""
    tb = withhlm.t_bin(data["k"])
    qb = np.searchsorted(withhlm.Q_EDGES, data["logq"], side="right")
    ang = data["ang"]
    r = np.where(ang, wrap(data["y"] - data["D"]), data["y"] - data["D"])
    dd = np.where(ang, wrap(data["H"] - data["D"]), data["H"] - data["D"])
    if tau > 0:
        dd = dd + data["o"] * np.exp(-1.0 / tau) ** (data["k"] - 1)
    return tb, qb, r, dd


BY_ACTIVITY = False   # True: also the smallest weight over activities (on validation: costs walks, no gain elsewhere)
COVER_EACH = 0.92    # share within 2 std asked of each activity in a cell (the pooled cell: 0.95)
MIN_VALUES = 100  # per fold and cell; fewer: the cell takes the limbs' pooled weight


def _ls(r, dd, sel, fold, act):
    """The smallest least-squares weight over the two folds by take and, within the cell, over every
    activity with MIN_VALUES values in it (a cell leans to default unless each half and each
    activity gains); None where a fold has fewer."""
    ws = []
    for f in (0, 1):
        m = sel & (fold == f)
        if m.sum() < MIN_VALUES:
            return None
        ws.append(float(np.sum(r[m] * dd[m]) / max(np.sum(dd[m] ** 2), 1e-9)))
    if BY_ACTIVITY:
        for a in np.unique(act[sel]):
            m = sel & (act == a)
            if m.sum() >= MIN_VALUES:
                ws.append(float(np.sum(r[m] * dd[m]) / max(np.sum(dd[m] ** 2), 1e-9)))
    return float(np.clip(min(ws), 0.0, withhlm.W_MAX))


def fit(data: dict[str, np.ndarray], tau: float) -> tuple[np.ndarray, np.ndarray]:
    G, TB, QB = len(withhlm.GROUP_NAMES), len(withhlm.T_EDGES) + 1, len(withhlm.Q_EDGES) + 1
    tb, qb, r, dd = parts(data, tau)
    fold = data["take"] % 2
    limbs = np.isin(data["g"], withhlm.SHADOW_GROUPS)
    W = np.zeros((G, TB, QB))
    for q in range(QB - 1, -1, -1):   # from the least evidence to the most
        for t in range(TB):
            pooled = _ls(r, dd, limbs & (tb == t) & (qb == q), fold, data['act'])
            if pooled is None and q < QB - 2:
                # no values at this much evidence (Q_PRIOR_N keeps validation streams off the first
                # bin): the share of the next bin, so stronger evidence never gets a smaller share
                W[:, t, q] = W[:, t, q + 1]
                continue
            for g in range(G):
                own = _ls(r, dd, (data["g"] == g) & (tb == t) & (qb == q), fold, data['act'])
                if own is None and t == TB - 1:   # past the last bin's data (gaps over 2 s): the last bin's weight
                    own = W[g, t - 1, q]
                W[g, t, q] = own if own is not None else ((pooled or 0.0) if g in withhlm.SHADOW_GROUPS else 0.0)
    W[withhlm.ROOT_POS] = 0.0
    W[:, :, -1] = 0.0    # as the model does (blend.withhlm): q > 1.1 yields to default
    w = W[data["g"], tb, qb]
    var = (1 - w) * data["sD"] ** 2 + w * data["sH"] ** 2 + w * (1 - w) * dd ** 2
    e = r - w * dd
    z = np.abs(e) / np.maximum(np.sqrt(var), 1e-9)
    S = np.ones((G, TB))
    for g in range(G):
        for t in range(TB):
            cell = (data["g"] == g) & (tb == t)
            if cell.sum() < MIN_VALUES:
                continue
            # 95% over the cell, and at least COVER_EACH in every activity with values in it
            qs = [np.quantile(z[cell], 0.95)] + [np.quantile(z[m], COVER_EACH) for a in range(4)
                                                 if (m := cell & (data["act"] == a)).sum() >= MIN_VALUES]
            S[g, t] = float(max(qs) / 2.0)
    return W, S


def report(data: dict[str, np.ndarray], W: np.ndarray, S: np.ndarray, tau: float, quiet: bool = False) -> dict:
    tb, qb, r, dd = parts(data, tau)
    ang = data["ang"]
    w = W[data["g"], tb, qb]
    var = (1 - w) * data["sD"] ** 2 + w * data["sH"] ** 2 + w * (1 - w) * dd ** 2
    sd = S[data["g"], tb] * np.sqrt(var)
    e = r - w * dd
    out = {}
    for pat in (False, True):
        for a, act in enumerate(("walk", "turn", "run", "nonloco")):
            m = ang & (data["act"] == a) & (data["pat"] == pat)
            if not m.any():
                continue
            rms = lambda v: float(np.sqrt(np.mean(v[m] ** 2)))  # noqa: E731
            key = f"{'pan2009' if pat else 'gaps'}/{act}"
            out[key] = {"default": rms(r), "hlm": rms(r - dd), "blend": rms(e),
                        "within2": float(np.mean(np.abs(e[m]) <= 2 * sd[m])), "n": int(m.sum())}
            if not quiet:
                print(f"{key:16s} default {out[key]['default']:6.2f}  hlm {out[key]['hlm']:6.2f}  blend {out[key]['blend']:6.2f}  "
                      f"within 2 std {out[key]['within2']:.3f}  ({out[key]['n']} values)")
    return out


def worst(data: dict[str, np.ndarray], W: np.ndarray, tau: float) -> tuple[float, str]:
    """The largest blend / default RMS over the take x pattern rows (angles), and which row."""
    tb, qb, r, dd = parts(data, tau)
    e = r - W[data["g"], tb, qb] * dd
    takes = sorted(splits.VALIDATION)
    out = (0.0, "")
    for t in np.unique(data["take"]):
        for pat in (False, True):
            m = data["ang"] & (data["take"] == t) & (data["pat"] == pat)
            if m.sum() >= MIN_VALUES:
                v = float(np.sqrt(np.mean(e[m] ** 2) / max(np.mean(r[m] ** 2), 1e-12)))
                out = max(out, (v, f"{takes[t]}{' pan2009' if pat else ''}"))
    return out


STRESS_MARGIN = 1.05   # what a stress case was asked to keep within, x the blend alone (not reached: robust-5.md)
SCORE_TOL = 0.005      # --stress: policies this close to the best validation mean are told apart by the stress


def stress(model: withhlm.WithHLMModel, W: np.ndarray, S: np.ndarray, tau: float, seeds: str) -> tuple[float, float, str]:
    """bench/default_stress.py's VALIDATION cases under the current policy with these W, S, tau: the
    largest default / blend over the cases, the mean, and the worst case."""
    import argparse as _ap

    import default_stress as ds

    m = withhlm.WithHLMModel(model.default, model.hlm, W, S, tau=tau)
    args = _ap.Namespace(kinds="gaps,crop,splice", seeds=seeds, activity="nonloco", max_frames=1000, crop_step=150)
    ratios = []
    for _kind, label, _act, x, obs in ds.cases(args):
        e = ds.run(m, x, obs)
        if e is not None:
            ratios.append((e["default"] / e["blend"], label))
    worst_case = max(ratios)
    return worst_case[0], float(np.mean([r for r, _ in ratios])), worst_case[1]


def sweep(model: withhlm.WithHLMModel, policies: list[tuple], cache: str | None, stress_seeds: str | None = None):
    """Per policy (Q_Z, SHADOW_SKIP, SHADOW_MAX_MISS, SHADOW_WARM, SHADOW_EAGER, Q_PRIOR_N, SHADOW_REVOKE)
    a fresh collection (the q bins depend on it), W/S fitted per tau;
    the policy kept: the lowest mean blend/default over the activity cells among those whose worst
    take x pattern row is at most ``default``'s own (a policy that makes any validation take worse than
    the blend alone is not kept while another is not), else the lowest worst.  With ``stress_seeds``
    each policy's best tau is also run on bench/default_stress.py's VALIDATION cases, then among the policies whose mean is within SCORE_TOL of the best mean (the noise of a 5-cell
    mean, bench/notebook/mixq-4.md) the one with the lowest worst stress case is kept (no stress:
    the lowest mean).  The STRESS_MARGIN of 1.05 was asked first: no policy tried reached it
    (bench/notebook/robust-5.md)."""
    done: list[tuple[float, tuple]] = []
    for pol in policies:
        z, skip, mm, warm, eager, prior, revoke = pol
        (withhlm.Q_Z, withhlm.SHADOW_SKIP, withhlm.SHADOW_MAX_MISS, withhlm.SHADOW_WARM, withhlm.SHADOW_EAGER,
         withhlm.Q_PRIOR_N, withhlm.SHADOW_REVOKE) = pol
        path = (f"{cache}-z{z:g}-s{skip}-m{mm}" + (f"-w{warm}-e{eager}" if warm or eager else "")
                + (f"-p{prior:g}-r{revoke:g}" if prior or revoke else "") + ".npz") if cache else None
        if path and Path(path).exists():
            data = dict(np.load(path))
        else:
            data = collect(model)
            if path:
                np.savez(path, **data)
        mine = None
        for tau in TAUS:
            W, S = fit(data, tau)
            res = report(data, W, S, tau, quiet=True)
            score = float(np.mean([v["blend"] / v["default"] for v in res.values()]))
            bad, where = worst(data, W, tau)
            print(f"Q_Z {z:g} SHADOW_SKIP {skip} SHADOW_MAX_MISS {mm} SHADOW_WARM {warm} SHADOW_EAGER {eager} "
                  f"Q_PRIOR_N {prior:g} SHADOW_REVOKE {revoke:g} tau {tau:5.0f}: blend / default mean over the cells {score:.4f}, "
                  f"worst take {bad:.4f} ({where})", flush=True)
            key = (bad > 1.0 + 1e-3, bad if bad > 1.0 + 1e-3 else score)
            if mine is None or key < mine[0]:
                mine = (key, pol, tau, W, S, data, score, bad, where)
        assert mine is not None
        smax = 0.0
        if stress_seeds:
            smax, smean, scase = stress(model, mine[3], mine[4], mine[2], stress_seeds)
            print(f"  stress (tau {mine[2]:g}): default / blend max {smax:.4f} ({scase}), mean {smean:.4f}", flush=True)
        done.append((smax, mine))
    ok = [d for d in done if not d[1][0][0]] or done
    top = min(d[1][0][1] for d in ok)
    near = [d for d in ok if d[1][0][1] <= top + SCORE_TOL]   # within the noise of the best mean
    smax, mine = min(near, key=lambda d: (d[0], d[1][0]))
    return (None, *mine[1:])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--default", help="a default model file trained on splits.TRAIN")
    ap.add_argument("--hlm", help="an hlm model file trained on the locomotion takes of splits.TRAIN")
    ap.add_argument("--write", action="store_true", help="write blend/withhlm.json")
    ap.add_argument("--cache", help="prefix of npz files of collected values, one per policy (read if it exists, else written)")
    ap.add_argument("--z", type=float, nargs="+", default=[withhlm.Q_Z], help="Q_Z values to try")
    ap.add_argument("--skip", type=int, nargs="+", default=[withhlm.SHADOW_SKIP], help="SHADOW_SKIP values to try")
    ap.add_argument("--max-miss", type=int, nargs="+", default=[withhlm.SHADOW_MAX_MISS], help="SHADOW_MAX_MISS values to try")
    ap.add_argument("--warm", type=int, nargs="+", default=[withhlm.SHADOW_WARM], help="SHADOW_WARM values to try")
    ap.add_argument("--eager", type=int, nargs="+", default=[withhlm.SHADOW_EAGER], help="SHADOW_EAGER values to try")
    ap.add_argument("--prior-at", type=float, default=withhlm.Q_PRIOR_AT, help="Q_PRIOR_AT (log r of the prior windows)")
    ap.add_argument("--prior", type=float, nargs="+", default=[withhlm.Q_PRIOR_N], help="Q_PRIOR_N values to try")
    ap.add_argument("--revoke", type=float, nargs="+", default=[withhlm.SHADOW_REVOKE], help="SHADOW_REVOKE values to try (0: off)")
    ap.add_argument("--stress", metavar="SEEDS", help="also run bench/default_stress.py's cases (gaps seeds SEEDS) per policy")
    a = ap.parse_args()
    withhlm.Q_PRIOR_AT = a.prior_at
    import blend.methods  # noqa: F401  (loaders)

    if a.default and a.hlm:
        d, h = modelfile.load_model(a.default), modelfile.load_model(a.hlm)
        model = withhlm.WithHLMModel(d, h, *withhlm.shipped()[:2])
    else:
        model = withhlm.train_model(protocols.Gaps().training_set(), cycle_frames=140)
    shipped_policy = (withhlm.Q_Z, withhlm.SHADOW_SKIP, withhlm.SHADOW_MAX_MISS, withhlm.SHADOW_WARM, withhlm.SHADOW_EAGER,
                      withhlm.Q_PRIOR_N, withhlm.SHADOW_REVOKE)
    policies = [(z, k, m, w, e, p, r) for z in a.z for k in a.skip for m in a.max_miss for w in a.warm
                for e in a.eager for p in a.prior for r in a.revoke]
    _, pol, tau, W, S, data, score, bad, where = sweep(model, policies, a.cache, a.stress)
    z, skip, mm, warm, eager, prior, revoke = pol
    print(f"chosen Q_Z {z:g}, SHADOW_SKIP {skip}, SHADOW_MAX_MISS {mm}, SHADOW_WARM {warm}, SHADOW_EAGER {eager}, "
          f"Q_PRIOR_N {prior:g}, SHADOW_REVOKE {revoke}, "
          f"tau {tau:g} frames (mean {score:.4f}, worst take {bad:.4f} {where})")
    if pol != shipped_policy:
        print(f"NOTE: set Q_Z, SHADOW_SKIP, SHADOW_MAX_MISS, SHADOW_WARM, SHADOW_EAGER, Q_PRIOR_N, SHADOW_REVOKE = {pol} in blend/withhlm.py "
              f"(the code ships {shipped_policy})")
    print("W (group x time bin) at each q bin:")
    for q in range(W.shape[2]):
        print(f" q bin {q}:")
        for g, name in enumerate(withhlm.GROUP_NAMES):
            print(f"  {name:10s} " + " ".join(f"{v:4.2f}" for v in W[g, :, q]))
    res = report(data, W, S, tau)
    if a.write:
        chosen = {"fitted_on": "VALIDATION: gaps bursts seeds " + ",".join(map(str, SEEDS)) + " + pan2009 pattern on its walks",
                  "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"), "tau": tau, "validation": res,
                  "policy": {"Q_Z": z, "SHADOW_SKIP": skip, "SHADOW_MAX_MISS": mm, "SHADOW_WARM": warm,
                             "SHADOW_EAGER": eager, "Q_PRIOR_N": prior, "Q_PRIOR_AT": withhlm.Q_PRIOR_AT,
                             "SHADOW_REVOKE": revoke, "worst_take": [round(bad, 4), where]}}
        out = {"W": W.round(4).tolist(), "S": S.round(4).tolist(), "chosen": chosen}
        old = json.loads(withhlm.SHIPPED.read_text()) if withhlm.SHIPPED.exists() else {}
        for key, val in old.get("chosen", {}).items():   # choices this tune does not make (the smoothing's): kept
            if key not in chosen:
                chosen[key] = val
                print(f"kept chosen \"{key}\" as it was")
        for key, how in (("calib", "bench/default_calib.py fit --write"), ("band_q", "bench/default_band_q.py --write")):
            if key in old:   # kept as it was, fitted on the old W/S: refit it after a W/S change
                out[key] = old[key]
                print(f"kept \"{key}\" as it was: refit it ({how})")
        withhlm.SHIPPED.write_text(json.dumps(out, indent=1) + "\n")
        print(f"wrote {withhlm.SHIPPED}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
