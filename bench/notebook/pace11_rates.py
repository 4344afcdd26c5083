"""pace-11's look at the rates (not a score): VALIDATION gaps seeds 100-102, the observed body's fast rate
R (the median over observed angle channels of decayed mean |dx| / rate_ref; tau 15, 40, 120 frames) at
erased angle values, quantiles per activity.  Argument: a model file with rate_ref (/tmp/nl49/train.npz)."""
import sys

import numpy as np

import blend.methods  # noqa: F401
from lacuna.modelfile import load_model
from mocap import protocols, splits
from mocap.representation import is_angle
from mocap.rootrot import wrap180 as wrap

m = load_model(sys.argv[1] if len(sys.argv) > 1 else "/tmp/nl49/train.npz")
ref = m.rate_ref
ang = np.array([is_angle(c) for c in m.channels])
res: dict = {}
for sd in (100, 101, 102):
    for c in protocols.Gaps(seed=sd, split="validation").cases():
        x, O = c.truth, c.observed
        T, C = x.shape
        out = {}
        for tau in (15, 40, 120):
            d = np.exp(-1 / tau)
            s, n, R = np.zeros(C), np.zeros(C), np.full(T, -1.0)
            for t in range(1, T):
                u = O[t] & O[t - 1]
                dx = np.abs(np.where(ang, wrap(x[t] - x[t - 1]), x[t] - x[t - 1]))
                s, n = np.where(u, s * d + dx, s), np.where(u, n * d + 1, n)
                ok = O[t] & ang & (ref > 0) & (n >= 1)
                if ok.any():
                    R[t] = np.median(s[ok] / n[ok] / ref[ok])
            out[tau] = R
        miss = ~O & ang[None]
        act = splits.ACTIVITY[c.test]
        res.setdefault(act, {15: [], 40: [], 120: []})
        for tau in out:
            res[act][tau].append(np.repeat(out[tau], miss.sum(1)))
for act, dd in res.items():
    for tau, v in dd.items():
        v = np.concatenate(v)
        v = v[v >= 0]
        q = np.quantile(v, [0.01, 0.05, 0.1, 0.25, 0.5])
        print(act, tau, " ".join(f"{k} {x:.3f}" for k, x in zip(("q01", "q05", "q10", "q25", "med"), q)),
              " ".join(f"share<{a} {(v < a).mean():.3f}" for a in (0.1, 0.2, 0.3)))
