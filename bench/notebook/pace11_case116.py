"""pace-11's look at one case: 49_19 under the gaps protocol at a seed (argument; robust-10's 116), each
rfemur.rx gap of 60+ frames: the observed body's slow rate (tau 120) at the onset, its fast rate (tau 15)
through the gap, the left leg's fast rate, the truth's own step.  Model file /tmp/nl49/train.npz (rate_ref)."""
import sys

import numpy as np

import blend.methods  # noqa: F401
from lacuna.modelfile import load_model
from mocap import protocols
from mocap.representation import is_angle
from mocap.rootrot import wrap180 as wrap

m = load_model("/tmp/nl49/train.npz")
ref, ch = m.rate_ref, m.channels
ang = np.array([is_angle(c) for c in ch])
seed = int(sys.argv[1]) if len(sys.argv) > 1 else 116
c = [c for c in protocols.Gaps(seed=seed, split="validation").cases() if c.test == "49_19"][0]
x, O = c.truth, c.observed
T, C = x.shape
j = ch.index("rfemur.rx")
d, d2 = np.exp(-1 / 15), np.exp(-1 / 120)
s, n, s2, n2 = np.zeros(C), np.zeros(C), np.zeros(C), np.zeros(C)
R, R2, Rl = np.full(T, -1.0), np.full(T, -1.0), np.full(T, -1.0)
lf = [i for i, nm in enumerate(ch) if nm.startswith("lfemur") or nm.startswith("ltibia")]
for t in range(1, T):
    u = O[t] & O[t - 1]
    dx = np.abs(np.where(ang, wrap(x[t] - x[t - 1]), x[t] - x[t - 1]))
    s, n = np.where(u, s * d + dx, s), np.where(u, n * d + 1, n)
    s2, n2 = np.where(u, s2 * d2 + dx, s2), np.where(u, n2 * d2 + 1, n2)
    ok = O[t] & ang & (ref > 0) & (n >= 1)
    if ok.any():
        R[t] = np.median(s[ok] / n[ok] / ref[ok])
        R2[t] = np.median(s2[ok] / n2[ok] / ref[ok])
    okl = [i for i in lf if ok[i]]
    if okl:
        Rl[t] = np.median(s[okl] / n[okl] / ref[okl])
miss = ~O[:, j]
for a in np.flatnonzero(miss & ~np.r_[False, miss[:-1]]):
    b = a
    while b < T and miss[b]:
        b += 1
    if b - a < 60:
        continue
    print(f"gap {a}-{b} ({b - a} frames): the body's slow rate at the onset {R2[a]:.3f}")
    for t in range(a, b, max(1, (b - a) // 10)):
        print(f"   t {t}: fast {R[t]:.3f} (x onset {R[t] / R2[a]:.2f}), left leg fast {Rl[t]:.3f}, "
              f"truth's step {abs(wrap(x[t, j] - x[t - 1, j])):.3f}, observed channels {O[t].sum()}")
