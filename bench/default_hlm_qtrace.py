"""Trace ``default``'s online check over a take: every shadow window's group, its frames, the HLM's and
the twin's squared errors on the hidden angles, split by frames into the window, raw and anchored
(the HLM's fill started where the twin starts, as the mixing does), and q after it.  A diagnostic
for VALIDATION takes (bench/notebook/mixq-4.md); nothing is chosen from it on TEST.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/default_hlm_qtrace.py MODEL.npz --protocol pan2009 --take walking_21
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from blend import withhlm  # noqa: E402
from lacuna import modelfile  # noqa: E402
from mocap import protocols, splits  # noqa: E402
from mocap.rootrot import wrap180 as wrap  # noqa: E402

EDGES = (0, 15, 30, 60)   # frames into the window


def trace(model: withhlm.WithHLMModel, case, verbose: bool = True) -> list[dict]:
    st = model.stream()
    wins: list[dict] = []
    cur: dict = {}
    orig = model._mix_fast if model.compiled else model._mix_numpy
    a = model.anchor

    def spy(states, F, O, HO, dfills, hfills, twin):
        s = states[0]
        T = twin.get(0)
        if T is not None:
            hid = O[0] & ~HO[0] & model.ang
            if hid.any():
                H = hfills[0].frame
                j = cur.setdefault("n", 0)
                if j == 0:
                    cur["o"] = wrap(T - H)
                    cur["g"] = withhlm.SHADOW_GROUPS[s.sh]
                    cur["t"] = t_now[0]
                    cur["eh"], cur["ea"], cur["e0"] = (np.zeros(len(EDGES)) for _ in range(3))
                b = np.searchsorted(EDGES, j, side="right") - 1
                eh = wrap(H - F[0])[hid]
                ea = wrap(H + cur["o"] * a ** j - F[0])[hid]
                e0 = wrap(T - F[0])[hid]
                cur["eh"][b] += (eh ** 2).sum()
                cur["ea"][b] += (ea ** 2).sum()
                cur["e0"][b] += (e0 ** 2).sum()
                cur["n"] = j + 1
        return orig(states, F, O, HO, dfills, hfills, twin)

    close = st._close

    def logged_close():
        close()
        if cur:
            wins.append({**cur, "q": float(np.exp(st.logq))})
            cur.clear()

    st._close = logged_close
    if model.compiled:
        model._mix_fast = spy
    else:
        model._mix_numpy = spy
    t_now = [0]
    try:
        for t in range(case.truth.shape[0]):
            t_now[0] = t
            st.step(case.truth[t], case.observed[t])
    finally:
        del model._mix_fast
        model.__dict__.pop("_mix_numpy", None)
    if verbose:
        miss = (~case.observed).sum(1)
        first = int(np.argmax(miss > withhlm.SHADOW_MAX_MISS)) if (miss > withhlm.SHADOW_MAX_MISS).any() else -1
        print(f"{case.test} {case.erased}: {len(wins)} windows, first frame with > {withhlm.SHADOW_MAX_MISS} missing: {first}, "
              f"q at end {np.exp(st.logq):.2f}")
        print("   t  group       n   r(raw) r(anch) | r by frames into window " + " ".join(f"{e}+" for e in EDGES) + " (anchored) |  q")
        for w in wins:
            r = w["eh"].sum() / max(w["e0"].sum(), 1e-9)
            ra = w["ea"].sum() / max(w["e0"].sum(), 1e-9)
            rb = " ".join(f"{x / max(y, 1e-9):5.2f}" for x, y in zip(w["ea"], w["e0"], strict=True))
            print(f"{w['t']:5d} {withhlm.GROUP_NAMES[w['g']]:10s} {w['n']:3d} {r:7.2f} {ra:7.2f} | {rb} | {w['q']:.2f}")
    return wins


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model")
    ap.add_argument("--protocol", choices=("pan2009", "gaps"), default="pan2009")
    ap.add_argument("--split", default="validation", choices=("validation",))
    ap.add_argument("--take", action="append")
    ap.add_argument("--seed", type=int, default=100)
    a = ap.parse_args()
    import blend.methods  # noqa: F401

    model = modelfile.load_model(a.model)
    proto = protocols.Pan2009(split=a.split) if a.protocol == "pan2009" else protocols.Gaps(seed=a.seed, split=a.split)
    for c in proto.cases():
        if c.test not in splits.VALIDATION:
            raise SystemExit(f"{c.test} is not a VALIDATION take")
        if a.take and c.test not in a.take:
            continue
        trace(model, c)
    return 0


if __name__ == "__main__":
    sys.exit(main())
