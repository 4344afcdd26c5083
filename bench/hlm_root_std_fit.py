"""Fit and check the std of a missing root's ground position (``Representation.root_std``:
sigma(g) = a g^(p-1) (Q(g) + c g) after g missing frames, Q summed over the gap of the filled speed,
the part the damping kept weighted w, the part it dropped 1, and u x the kept part of the model's
own std).

    collect: .venv/bin/python bench/hlm_root_std_fit.py collect MODEL.npz --split validation --seeds 3 --out F.npz
    fit:     .venv/bin/python bench/hlm_root_std_fit.py fit F.npz[,G.npz ...]
    check:   .venv/bin/python bench/hlm_root_std_fit.py check MODEL.npz --split test --seeds 3 --rule a,p,c,w,u

``collect`` fills every root-erased case (``bench/hlm_validation.py``'s ``gaps+root`` and
``legs-only``) three times, with the rules [1, 1, 0, 1, 0], [1, 1, 0, 0, 0] and [], whose stds are
L(g) (all the filled speed), D(g) (its dropped part) and S(g) + D(g) (S the kept part of the
model's std), and keeps (g, error, L, D, S) per missing frame and activity; ``fit``
prints the grid (p, c, w, a) whose shares within 2 std all lie in [0.91, 0.97] (coverage only), then
the maximum-likelihood (Gaussian NLL) rule, kept in hlm.methods.DEFAULTS, and what forcing the
coverage onto it costs; ``check`` runs the real
pipeline with a rule (and the summed std, "old") and prints within 1 / 2 std and the Gaussian NLL
per activity.  The error is 2-D, compared per axis as |e| / sqrt(2) (as hlm_root_calibration.py).
The model's root damping is set to hlm.methods.DEFAULTS' (root_tau 40, root_turn 8, W 60).
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from hlm_validation import CM_PER_UNIT, make_cases  # noqa: E402

from lacuna.modelfile import load_model  # noqa: E402
from mocap import splits  # noqa: E402

DAMP = dict(root_tau=40.0, root_turn=8.0, root_turn_frames=60.0)


def _gap_index(miss: np.ndarray) -> np.ndarray:
    """1-based frames missing so far (g) for each frame of a missing run."""
    g = np.zeros(miss.shape[0])
    run = 0
    for t, m in enumerate(miss):
        run = run + 1 if m else 0
        g[t] = run
    return g


def run_cases(model, takes: list[str], seeds: int, rule) -> dict[str, list[np.ndarray]]:
    """activity -> [(g, error, std) rows per missing root frame]."""
    m = model.with_options(**DAMP, root_std=rule)
    out: dict[str, list[np.ndarray]] = {}
    for c in make_cases(takes, seeds):
        if c["kind"] == "gaps":
            continue
        ch = c["channels"]
        px, pz = ch.index("root.tx"), ch.index("root.tz")
        fill, sd = m.fill_offline(np.where(c["obs"], c["truth"], np.nan), c["obs"].copy())
        miss = ~c["obs"][:, px]
        e = np.hypot(fill[:, px] - c["truth"][:, px], fill[:, pz] - c["truth"][:, pz]) / np.sqrt(2.0)
        g = _gap_index(miss)
        out.setdefault(splits.ACTIVITY[c["take"]], []).append(np.stack([g[miss], e[miss], sd[miss, px]], 1))
    return out


def summary(rows: np.ndarray) -> tuple[float, float, float, float]:
    e, s = rows[:, 1], np.maximum(rows[:, 2], 1e-9)
    r = e / s
    # Gaussian NLL of the 2-D error (both axes the same std), nats per frame, in cm
    s_cm, e_cm = s * CM_PER_UNIT, e * CM_PER_UNIT
    nll = np.mean(np.log(2 * np.pi * s_cm**2) + e_cm**2 / s_cm**2)
    return float(np.mean(r <= 1)), float(np.mean(r <= 2)), float(nll), float(np.median(s_cm))


def ml_fit(d, acts: list[str]) -> None:
    """The kept fit: the mean over groups (activity, or model x activity) of the Gaussian NLL
    minimised (Nelder-Mead, four starts, one of them the summed std) over log a, p, log c, log w,
    log u; then with a penalty on shares within 2 std outside [0.91, 0.97] (pen > 0), to see what
    forcing the coverage costs."""
    from scipy.optimize import minimize

    def sig(r, th):
        la, p, lc, lw, lu = th
        q = np.exp(lw) * (r[:, 2] - r[:, 3]) + r[:, 3] + np.exp(lu) * r[:, 4] + np.exp(lc) * r[:, 0]
        return np.exp(la) * r[:, 0] ** (p - 1) * q + 1e-9

    def stats(th):
        out = {}
        for a in acts:
            r = d[a]
            s, e = sig(r, th) * CM_PER_UNIT, r[:, 1] * CM_PER_UNIT
            out[a] = (np.mean(e <= s), np.mean(e <= 2 * s), np.mean(np.log(2 * np.pi * s**2) + e**2 / s**2))
        return out

    def obj(th, pen):
        st = stats(th)
        cov = sum(max(0, 0.91 - v[1]) ** 2 + max(0, v[1] - 0.97) ** 2 for v in st.values())
        return np.mean([v[2] for v in st.values()]) + pen * cov

    print("summed std: " + " ".join(f"{a} {v[0]:.3f}/{v[1]:.3f}/{v[2]:.2f}"
                                    for a, v in stats([0.0, 1.0, np.log(1e-12), np.log(1e-12), 0.0]).items()))
    starts = ([np.log(0.1), 1.0, np.log(0.01), np.log(0.2), np.log(0.5)], [np.log(0.02), 1.5, np.log(0.05), 0.0, -3.0],
              [np.log(0.5), 0.7, np.log(0.1), np.log(0.05), np.log(0.1)], [0.0, 1.0, np.log(1e-4), np.log(1e-4), 0.0])
    for pen in (0.0, 1e3, 1e4):
        best = min((minimize(obj, x0, args=(pen,), method="Nelder-Mead",
                             options=dict(maxiter=4000, xatol=1e-4, fatol=1e-4)) for x0 in starts), key=lambda r: r.fun)
        th = best.x
        print(f"ML, penalty {pen:g}: a {np.exp(th[0]):.5g} p {th[1]:.4f} c {np.exp(th[2]):.5g} w {np.exp(th[3]):.5g} "
              f"u {np.exp(th[4]):.5g}: " + " ".join(f"{a} {v[0]:.3f}/{v[1]:.3f}/{v[2]:.2f}" for a, v in stats(th).items())
              + " (within 1/2 std, NLL)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cmd", choices=("collect", "fit", "check"))
    ap.add_argument("path")
    ap.add_argument("--split", choices=("validation", "test"), default="validation")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--out")
    ap.add_argument("--rule", help="a,p,c,w,u")
    args = ap.parse_args(argv)
    takes = splits.VALIDATION if args.split == "validation" else splits.TEST
    if args.cmd == "collect":
        if args.split != "validation":
            raise SystemExit("the rule is fitted on VALIDATION only")
        model = load_model(args.path)
        # std of [1, 1, 0, 1, 0] is L (all the filled speed), of [1, 1, 0, 0, 0] D (the part
        # dropped), the summed std's ([]) S + D, S the kept part of the model's own std
        full = run_cases(model, takes, args.seeds, [1.0, 1.0, 0.0, 1.0, 0.0])
        drop = run_cases(model, takes, args.seeds, [1.0, 1.0, 0.0, 0.0, 0.0])
        old = run_cases(model, takes, args.seeds, [])
        np.savez(args.out, **{a: np.column_stack([np.vstack(v), np.vstack(drop[a])[:, 2],
                                                  np.vstack(old[a])[:, 2] - np.vstack(drop[a])[:, 2]])
                              for a, v in full.items()})
        return 0
    if args.cmd == "fit":
        # several files (one per model): their groups are pooled as model:activity
        files = args.path.split(",")
        d = {(f"{i}:{a}" if len(files) > 1 else a): v for i, f in enumerate(files) for a, v in np.load(f).items()}
        acts = list(d.keys())
        # (u 0) every (p, c, w, a) on the grid with all activities' share within 2 std in [0.91, 0.97]
        # (issue 17's 0.90-0.98 with a margin); kept: the smallest mean over activities of the NLL.
        # c = w = 0 is left out (the std would be 0 for a performer seen not turning at all).
        feas, best_w = [], None
        for p in (0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2, 1.3, 1.4, 1.5, 1.75, 2.0, 2.5, 3.0):
            for c in (0.0, 0.001, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0):
                for w in (0.0, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0):
                    if c == 0.0 and w == 0.0:
                        continue
                    base = {act: np.maximum(d[act][:, 0] ** (p - 1.0) * (w * (d[act][:, 2] - d[act][:, 3])
                                                                        + d[act][:, 3] + c * d[act][:, 0]), 1e-12)
                            for act in acts}
                    ratio = {act: d[act][:, 1] / base[act] for act in acts}
                    a0 = float(np.quantile(np.concatenate(list(ratio.values())), 0.95) / 2.0)
                    for a in a0 * np.exp(np.linspace(-2, 2, 81)):
                        shares = {act: float(np.mean(ratio[act] <= 2 * a)) for act in acts}
                        worst = max(abs(v - 0.95) for v in shares.values())
                        if best_w is None or worst < best_w[0]:
                            best_w = (worst, a, p, c, w, shares)
                        if all(0.91 <= v <= 0.97 for v in shares.values()):
                            nll = {}
                            for act in acts:
                                s_cm, e_cm = a * base[act] * CM_PER_UNIT, d[act][:, 1] * CM_PER_UNIT
                                nll[act] = float(np.mean(np.log(2 * np.pi * s_cm**2) + e_cm**2 / s_cm**2))
                            feas.append((float(np.mean(list(nll.values()))), a, p, c, w, shares, nll))
        worst, a, p, c, w, shares = best_w
        print(f"nearest 95% everywhere: a {a:.5g} p {p:.3g} c {c:g} w {w:g} (worst |share - 0.95| {worst:.3f}): "
              + " ".join(f"{k} {v:.3f}" for k, v in shares.items()))
        feas.sort(key=lambda f: f[0])
        print(f"{len(feas)} feasible; the 8 of smallest mean NLL (and the best per p):")
        seen = set()
        for i, (m, a, p, c, w, shares, nll) in enumerate(feas):
            if i < 8 or p not in seen:
                seen.add(p)
                print(f"  NLL {m:.3f}: a {a:.5g} p {p:g} c {c:g} w {w:g}: "
                      + " ".join(f"{k} {shares[k]:.3f}/{nll[k]:.2f}" for k in acts))
        ml_fit(d, acts)
        return 0
    rule = [float(v) for v in args.rule.split(",")]
    model = load_model(args.path)
    print("rule | activity | frames | within 1 std | within 2 std | NLL (nats per frame, 2-D, cm) | median std cm")
    for label, r in (("old", []), (args.rule, rule)):
        for act, v in sorted(run_cases(model, takes, args.seeds, r).items()):
            rows = np.vstack(v)
            w1, w2, nll, ms = summary(rows)
            print(f"{label} | {act} | {rows.shape[0]} | {w1:.3f} | {w2:.3f} | {nll:.2f} | {ms:.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
