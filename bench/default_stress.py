"""A stress of ``default``'s online check on VALIDATION takes only: many stream starts on motion the
HLM does not know, where one early shadow window may judge the HLM better by chance
(bench/notebook/robust-5.md).  Per case, RMS over the erased angles of ``default``, its blend alone
(``default-blend``, the expert) and hold; the worst ratios, and every case where ``default`` is worse
than the blend by more than a margin.

Cases (all from splits.VALIDATION; nothing from TEST or the papers' takes):
- ``gaps``: the gaps protocol's bursts at seeds --seeds on the validation takes up to --max-frames
  long (--activity picks them; nonloco by default);
- ``crop``: 400-frame crops of the long non-locomotion takes (basketball_signal_4, 49_19) at every
  --crop-step frames, each a new stream with the gaps bursts of seed 100 + its offset;
- ``splice``: a validation walk's first 5 s, then a non-locomotion take (root translation shifted to
  continue, 0.25 s clean after the seam): the HLM may earn its share on the walk, then must lose it.

    OPENBLAS_NUM_THREADS=1 nice -n 19 .venv/bin/python bench/default_stress.py MODEL.npz --seeds 100-139
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
from lacuna import modelfile  # noqa: E402
from mocap import protocols, splits  # noqa: E402
from mocap.cli import parse_seeds  # noqa: E402
from mocap.representation import is_angle  # noqa: E402
from mocap.rootrot import wrap180 as wrap  # noqa: E402

CROP = 400
LONG_NONLOCO = ("basketball_signal_4", "49_19")
SPLICE_WALKS = ("walking_20", "walking_21", "35_28")
WALK_FRAMES = 600


def seeds(spec: str) -> list[int]:
    return parse_seeds(spec, None)   # A-B or A,B,... as `lacuna eval --seeds`


def _mask(name: str, T: int, channels: list[str], seed: int, clean: list[tuple[int, int]] = ()) -> np.ndarray:
    obs, _ = protocols.Gaps(seed=seed, split="validation").occlusion(name, T, channels, 120.0)
    for a, b in clean:
        obs[a:b] = True
    return obs


def cases(a: argparse.Namespace):
    """(kind, label, activity, truth (T, C), observed (T, C))."""
    kinds = set(a.kinds.split(","))
    if "gaps" in kinds:
        takes = [t for t in splits.VALIDATION if splits.ACTIVITY[t] in a.activity.split(",")]
        for s in seeds(a.seeds):
            for c in protocols.Gaps(seed=s, split="validation").cases():
                if c.test in takes and c.truth.shape[0] <= a.max_frames:
                    yield "gaps", f"{c.test}@{s}", splits.ACTIVITY[c.test], c.truth, c.observed
    if "crop" in kinds:
        for t in LONG_NONLOCO:
            m = protocols.load_take(t)
            for off in range(0, m.n_frames - CROP + 1, a.crop_step):
                x = np.array(m.frames[off:off + CROP])
                yield "crop", f"{t}[{off}:]", "nonloco", x, _mask(f"{t}-{off}", CROP, m.channels, 100 + off)
    if "splice" in kinds:
        for w in SPLICE_WALKS:
            for t in [t for t in splits.VALIDATION if splits.ACTIVITY[t] == "nonloco"]:
                x, n1 = splice(w, t)
                obs = _mask(f"{w}+{t}", len(x), protocols.load_take(w).channels, 100, [(n1, n1 + 30)])
                yield "splice", f"{w}+{t}", "nonloco", x, obs


def splice(walk: str, other: str) -> tuple[np.ndarray, int]:
    """The walk's first WALK_FRAMES frames, then ``other``'s first 1500 with its root translation moved
    to go on from where the walk stopped: (frames, the seam's frame)."""
    mw, mn = protocols.load_take(walk), protocols.load_take(other)
    x1, x2 = np.array(mw.frames[:WALK_FRAMES]), np.array(mn.frames[:1500])
    pos = [j for j, c in enumerate(mw.channels) if not is_angle(c)]
    x2[:, pos] += x1[-1, pos] - x2[0, pos]
    return np.concatenate([x1, x2]), len(x1)


def run(model: withhlm.WithHLMModel, x: np.ndarray, obs: np.ndarray, splice_at: int | None = None):
    st, bs = model.stream(), model.default.stream()
    ang = model.ang
    out = np.zeros_like(x)
    blend = np.zeros_like(x)
    hold = np.zeros_like(x)
    last = x[0].copy()
    for t in range(len(x)):
        out[t] = st.step(x[t], obs[t]).frame
        blend[t] = bs.step(x[t], obs[t]).frame
        last = np.where(obs[t], x[t], last)
        hold[t] = last
    m = ~obs & ang[None, :]
    if not m.any():
        return None
    e = {k: float(np.sqrt(np.mean(wrap(v - x)[m] ** 2))) for k, v in (("default", out), ("blend", blend), ("hold", hold))}
    e["n"] = int(m.sum())
    e["q_end"] = float(np.exp(st.logq))
    return e


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model")
    ap.add_argument("--seeds", default="100-119")
    ap.add_argument("--activity", default="nonloco")
    ap.add_argument("--kinds", default="gaps,crop,splice")
    ap.add_argument("--max-frames", type=int, default=1000, help="gaps: takes up to this long (the long ones are cropped)")
    ap.add_argument("--crop-step", type=int, default=150)
    ap.add_argument("--margin", type=float, default=1.02, help="list cases where default > margin x the blend")
    ap.add_argument("--json", help="write the per-case figures here")
    ap.add_argument("--policy", type=float, nargs=2, metavar=("Q_PRIOR_N", "SHADOW_REVOKE"),
                    help="run under this check instead of the module's (0 0: main 5b13b52's)")
    ap.add_argument("--gate-n0", type=float, help="run with this gate_n0 (checks before the regression's whole gate) instead of the file's")
    ap.add_argument("--n0", type=float, help="run with this guard_n0 (the ridge's strength) instead of the file's")
    ap.add_argument("--pace", type=float, nargs=3, metavar=("PACE_TAU", "PACE_K", "PACE_A"),
                    help="run with the fill's pace (blend/withhlm.py \"Pace\") set so instead of the file's")
    a = ap.parse_args()
    import blend.methods  # noqa: F401  (loaders)

    if a.policy:
        withhlm.Q_PRIOR_N, withhlm.SHADOW_REVOKE = a.policy
    model = modelfile.load_model(a.model)
    assert isinstance(model, withhlm.WithHLMModel)
    if a.gate_n0 is not None:
        model.default.settings.gate_n0 = a.gate_n0
        model.default._par[12] = a.gate_n0
    if a.n0 is not None:
        model.default.settings.guard_n0 = a.n0
        model.default.guard_par[1] = a.n0
    if a.pace is not None:
        model.set_smooth(**{**model.smooth, "pace_tau": a.pace[0], "pace_k": a.pace[1], "pace_a": a.pace[2]})
    rows = []
    t0 = time.time()
    for kind, label, act, x, obs in cases(a):
        e = run(model, x, obs)
        if e is None:
            continue
        rows.append({"kind": kind, "case": label, "act": act, **e})
    print(f"{len(rows)} cases, {time.time() - t0:.0f} s")
    for kind in sorted({r["kind"] for r in rows}):
        rs = [r for r in rows if r["kind"] == kind]
        rb = np.array([r["default"] / r["blend"] for r in rs])
        rh = np.array([r["default"] / r["hold"] for r in rs])
        pooled = {k: float(np.sqrt(sum(r[k] ** 2 * r["n"] for r in rs) / sum(r["n"] for r in rs))) for k in ("default", "blend", "hold")}
        print(f"{kind:7s} {len(rs):4d} cases: pooled RMS default {pooled['default']:.3f} blend {pooled['blend']:.3f} "
              f"hold {pooled['hold']:.3f}; default/blend max {rb.max():.3f} mean {rb.mean():.4f}, "
              f"cases > {a.margin} x blend: {int((rb > a.margin).sum())}; default > hold: {int((rh > 1).sum())} "
              f"(blend > hold: {sum(r['blend'] > r['hold'] for r in rs)})")
    bad = sorted(rows, key=lambda r: -r["default"] / r["blend"])[:12]
    print("worst default / blend:")
    for r in bad:
        print(f"  {r['kind']:7s} {r['case']:32s} default {r['default']:6.3f} blend {r['blend']:6.3f} hold {r['hold']:6.3f} "
              f"x blend {r['default'] / r['blend']:.3f}  q end {r['q_end']:.2f}")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=0))
    return 0


if __name__ == "__main__":
    sys.exit(main())
