"""The step cost of ``default``'s leg gate (blend/withhlm.py, "Long erasures"; bench/notebook/loco-12.md):
one model file loaded twice, A with the gate off, B with it set (--gate K QL), and the file's HLM alone
(H), stepped in turn frame by frame in one process (the order rotating every frame; ``step_block``,
the daemon's bundle path), one stream each, over a VALIDATION take: with the gaps protocol's bursts
(seed 0: the gate's windows never run) and with pan2009's pattern (every channel but the legs erased
from half way: scored from the erasure's onset, where the gate's twins run).  Medians of each, the
per-frame ratio B / A and B / H, A / H.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/loco12_stepcost.py MODEL.npz --gate 60 0.8 [--take walking_20] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from blend import withhlm  # noqa: E402
from lacuna.modelfile import load_model  # noqa: E402
from mocap import protocols, splits  # noqa: E402


def step3(A, B, F: np.ndarray, obs: np.ndarray, start: int, reps: int) -> dict[str, np.ndarray]:
    acc: dict[str, list[float]] = {"A": [], "B": [], "H": []}
    for _ in range(reps):
        sa, sb, sh = [A.stream()], [B.stream()], [A.hlm.stream()]
        jobs = [("A", lambda f, o: A.step_block(sa, f, o)), ("B", lambda f, o: B.step_block(sb, f, o)),
                ("H", lambda f, o: A.hlm.step_block(sh, f, o))]
        for t in range(F.shape[0]):
            f, o = np.ascontiguousarray(F[t:t + 1]), np.ascontiguousarray(obs[t:t + 1])
            k = t % 3
            for name, fn in jobs[k:] + jobs[:k]:
                t0 = time.perf_counter_ns()
                fn(f, o)
                if t >= start:
                    acc[name].append((time.perf_counter_ns() - t0) / 1000.0)
    return {k: np.array(v) for k, v in acc.items()}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("model")
    ap.add_argument("--gate", type=float, nargs="+", default=[60, 0.8], help="K QL [QR [REST]]")
    ap.add_argument("--ll", type=float, nargs=2, help="D TAU: B with long_ll (D, TAU) instead of the gate (loco-13)")
    ap.add_argument("--legs", action="store_true", help="with --ll: B with the legs-only baseline (long_ll_legs); A "
                    "then keeps the file's long_ll (loco-14: against the current setting, not off)")
    ap.add_argument("--take", default="walking_20")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--json")
    a = ap.parse_args()
    assert a.take in splits.VALIDATION
    import blend.methods  # noqa: F401  (loaders)

    m = splits.load_take(a.take)
    A, B = load_model(a.model), load_model(a.model)
    A.set_long_trust(*withhlm.LONG_TRUST_OFF)
    A.set_long_gate(*withhlm.LONG_GATE_OFF)
    B.set_long_trust(*withhlm.LONG_TRUST_OFF)
    if a.ll:
        B.set_long_ll(*a.ll)
        B.set_long_ll_legs(a.legs)
    else:
        B.set_long_gate(int(a.gate[0]), *a.gate[1:3], *[int(v) for v in a.gate[3:]])
    gobs, _ = protocols.Gaps(seed=0, split="validation").occlusion(a.take, m.n_frames, m.channels, m.fps)
    legs = np.isin(withhlm.group_index(list(m.channels)), withhlm.LEG_GROUPS)
    pobs = np.ones(m.frames.shape, bool)
    pobs[m.n_frames // 2:, ~legs] = False
    out: dict = {"model": a.model, "take": a.take, "gate": None if a.ll else a.gate, "ll": a.ll, "legs": a.legs, "load": list(os.getloadavg()), "cases": {}}
    for name, obs, start in (("gaps", gobs, 50), ("pan2009", pobs, m.n_frames // 2)):
        F = np.where(obs, m.frames, np.nan)
        t = step3(A, B, F, obs, start, a.reps)
        r = {k: float(np.median(v)) for k, v in t.items()}
        r.update({"B/A": float(np.median(t["B"] / t["A"])), "A/H": float(np.median(t["A"] / t["H"])),
                  "B/H": float(np.median(t["B"] / t["H"])), "frames": int(len(t["A"])),
                  "B/A mean": float(t["B"].mean() / t["A"].mean()), "B/A p90": float(np.quantile(t["B"] / t["A"], 0.9))})
        out["cases"][name] = r
        print(f"{name:8s}: off {r['A']:.1f} us, gate {r['B']:.1f} us, hlm {r['H']:.1f} us; per-frame ratio "
              f"gate/off {r['B/A']:.3f} (p90 {r['B/A p90']:.3f}; of the means {r['B/A mean']:.3f}), off/hlm {r['A/H']:.3f}, "
              f"gate/hlm {r['B/H']:.3f} ({r['frames']} frames)", flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
