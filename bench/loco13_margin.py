"""loco-13's margin (bench/notebook/loco-13.md, reported after the verdict): per take under pan2009's pattern
(every channel but the legs erased from half way), a model file with long_ll set: the stream's baseline B
frozen at the erasure's onset, the lowest erasure level from LL_N0 frames on, and how far above the revoke
bound B - D it stayed (negative: revoked).

    OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/loco13_margin.py MODEL.npz --ll 4,60 [--legs] TAKE...
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from blend import withhlm  # noqa: E402
from lacuna.modelfile import load_model  # noqa: E402
from mocap import protocols  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model")
    ap.add_argument("takes", nargs="+")
    ap.add_argument("--ll", default="4,60")
    ap.add_argument("--legs", action="store_true", help="the legs-only baseline (long_ll_legs, loco-14)")
    a = ap.parse_args()
    import blend.methods  # noqa: F401  (loaders)

    d, tau = (float(v) for v in a.ll.split(","))
    m = load_model(a.model)
    m.set_long_ll(d, tau)
    m.set_long_ll_legs(a.legs)
    legs = np.isin(withhlm.group_index(list(m.channels)), withhlm.LEG_GROUPS)
    for t in a.takes:
        x = np.array(protocols.load_take(t).frames)
        obs = np.ones(x.shape, bool)
        obs[len(x) // 2:, ~legs] = False
        st, lv = m.stream(), []
        for i in range(len(x)):
            st.step(np.where(obs[i], x[i], np.nan), obs[i])
            if st.ll_in and st.ll_age >= withhlm.LL_N0:
                lv.append(st.ll_S / st.ll_N)
        lo = min(lv) if lv else float("nan")
        print(f"{t:12s} baseline {st.ll_B:8.2f} (weight {st.ll_bN:5.0f})  erasure level min {lo:8.2f} median "
              f"{np.median(lv) if lv else float('nan'):8.2f}  margin above B - D {lo - (st.ll_B - d):7.2f}  revokes {st.n_llrev}",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
