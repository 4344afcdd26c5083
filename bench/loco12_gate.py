"""loco-12's candidates (bench/notebook/loco-12.md): copies of a saved ``default`` (trained by
bench/pan11_long_trust.py, the gate off) with the leg gate (blend/withhlm.py, "Long erasures") set,
each scored with ``lacuna eval --model FILE``; and ``--trace``: per take of pan2009 VALIDATION (and the
stress's long non-locomotion takes under pan2009's pattern) the gate's q_long+ and how often it is open.

    .venv/bin/python bench/loco12_gate.py BASE.npz --gate 120,1.1 --gate 120,0.8     # writes BASE_g120_1.1.npz ...
    .venv/bin/python bench/loco12_gate.py BASE_g120_1.1.npz --trace 35_28,49_19
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from blend import withhlm  # noqa: E402
from lacuna.modelfile import load_model  # noqa: E402
from mocap import protocols  # noqa: E402


def trace(m: withhlm.WithHLMModel, take: str) -> None:
    """pan2009's pattern on ``take`` (its second half erased but the legs): the gate per frame."""
    mt = protocols.load_take(take)
    x = np.array(mt.frames)
    ch = list(mt.channels)
    legs = np.isin(withhlm.group_index(ch), withhlm.LEG_GROUPS)
    obs = np.ones(x.shape, bool)
    obs[len(x) // 2:, ~legs] = False
    s = m.stream()
    qs, open_, lq, rev = [], 0, [], 0
    for t in range(len(x)):
        s.step(x[t], obs[t])
        if t >= len(x) // 2:
            qb = m._qb(s, obs[t])
            open_ += qb == len(withhlm.Q_EDGES) + 1
            rev += s.lbusy and m._lr_min < s.lg_lq < withhlm.LOGQ_UNSCORED
            lq.append(s.lg_lq)
            qs.append(s.logq)
    lq = np.array(lq)
    sc = lq[lq < withhlm.LOGQ_UNSCORED]
    print(f"{take}: erased {len(lq)} frames, q+ {math.exp(qs[-1]):.2f}, long windows scored {s.n_lwin}, "
          f"q_long+ end {math.exp(lq[-1]):.2f} (min {math.exp(sc.min()) if len(sc) else float('nan'):.2f}, "
          f"max {math.exp(sc.max()) if len(sc) else float('nan'):.2f}), "
          f"long bin on {open_} frames, revoked {rev}", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("base")
    ap.add_argument("--gate", action="append", default=[], help="K,QL[,QR[,REST]] (frames, q_long+ bounds: open, revoke; frames of rest between long windows)")
    ap.add_argument("--trace", help="takes (comma-separated) to trace under pan2009's pattern")
    a = ap.parse_args(argv)
    import blend.methods  # noqa: F401  (loaders)

    for g in a.gate:
        k, q, *r = g.split(",")
        m = load_model(a.base)
        m.set_long_trust(*withhlm.LONG_TRUST_OFF)
        m.set_long_gate(int(k), float(q), float(r[0]) if r else 0.0, int(r[1]) if len(r) > 1 else 0)
        out = a.base[:-4] + f"_g{k}_{q}" + "".join(f"_{v}" for v in r) + ".npz"
        m.save(out)
        print("wrote", out, flush=True)
    if a.trace:
        m = load_model(a.base)
        for t in a.trace.split(","):
            trace(m, t)
    return 0


if __name__ == "__main__":
    sys.exit(main())
