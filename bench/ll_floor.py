"""``default``'s floor on the HLM's own predictive likelihood (blend/withhlm.py ``set_ll_floor``) on
VALIDATION takes only, against the floor off: the gaps protocol (seeds 0-4, rms_deg per activity and per
take, beside hold), pan2009's VALIDATION walks (MSE per take), and one take held out of its own model's
training (13_39, CMU's jumps: the model trained on TRAIN without it, so its motion is new to the blend as
to the HLM).  One model per protocol, trained as ``lacuna eval`` trains it; every floor applied to it in
turn (a run-time setting of the mixing).  Nothing from TEST or the papers' test takes.

    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python bench/ll_floor.py --floors 0 -6 -9 -12 --tau 60 \\
        --json bench/results/ll_floor.json
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mocap import protocols, splits  # noqa: E402
from mocap.evaluate import evaluate, make_protocol, train  # noqa: E402

HELD = "13_39"


def rows(res: dict, metric: str) -> dict[str, float]:
    return {r["test"]: r["value"] for r in res["results"] if r["metric"] == metric and r["value"] is not None}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--floors", type=float, nargs="+", default=[0.0, -6.0, -9.0, -12.0])
    ap.add_argument("--tau", type=float, default=60.0)
    ap.add_argument("--seeds", default="0-4")
    ap.add_argument("--json")
    a = ap.parse_args()
    seeds = list(range(int(a.seeds.split("-")[0]), int(a.seeds.split("-")[-1]) + 1))
    t0 = time.perf_counter()
    log = lambda msg: print(f"[{time.perf_counter() - t0:5.0f} s] {msg}", file=sys.stderr, flush=True)  # noqa: E731
    models = {"gaps": train(make_protocol("gaps", 0, "validation", False), "default", {}, False, None, None)}
    log("trained gaps (TRAIN)")
    models["pan2009"] = train(make_protocol("pan2009", 0, "validation", False), "default", {}, False, None, None)
    log("trained pan2009 (its set minus validation and test)")
    loao = protocols.named_training_set([t for t in splits.TRAIN if t != HELD])
    from blend.withhlm import train_model

    models["held"] = train_model(loao, fps=120.0)
    log(f"trained TRAIN without {HELD}")
    out: dict = {"floors": a.floors, "tau": a.tau, "seeds": seeds, "runs": {}}
    hold = evaluate("gaps", "hold", split="validation", seeds=seeds, progress=False)
    out["hold_gaps"] = rows(hold, "rms_deg")
    out["hold_held"] = rows(evaluate("gaps", "hold", test_file=str(splits.take_path(HELD)), seeds=seeds, progress=False), "rms_deg")
    for L in a.floors:
        run = {}
        for m in models.values():
            m.set_ll_floor(L, a.tau if L < 0 else 0.0)
        g = evaluate("gaps", "default", model=models["gaps"], split="validation", seeds=seeds, progress=False)
        run["gaps_rms"] = rows(g, "rms_deg")
        run["gaps_within_2std"] = rows(g, "within_2std")
        p = evaluate("pan2009", "default", model=models["pan2009"], split="validation", progress=False)
        run["pan2009"] = {k: v for k, v in rows(p, "mse_deg2").items()}
        h = evaluate("gaps", "default", model=models["held"], test_file=str(splits.take_path(HELD)), seeds=seeds, progress=False)
        run["held_rms"] = rows(h, "rms_deg")
        out["runs"][str(L)] = run
        log(f"floor {L}: gaps {json.dumps({k: round(v, 4) for k, v in run['gaps_rms'].items()})}")
        log(f"          pan2009 {json.dumps({k: round(v, 3) for k, v in run['pan2009'].items()})}  {HELD} held out {run['held_rms']}")
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
