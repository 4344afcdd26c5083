"""taylor2007 (section 5): how much of the CRBM's error is the training seed's, and what
averaging independently seeded models buys.

Trains ``crbm-imp`` (hidden probabilities in the data term, parameters averaged over the last
20% of epochs, S = 8 chains) once per seed, scores each with the protocol's cumulative scaled
error as a ratio to the better nearest neighbour, then scores the ensemble whose fill is the
mean of the members' fills (the chains of all members pooled).  Trained models are kept in
--cache and reused.

    .venv/bin/python bench/crbm_seed_ensemble.py --seeds 0 1 2 3 4 [--epochs 2000] [--repeats 3] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

import numpy as np  # noqa: E402

from crbm.experiment import baseline_scores, ratios, score_model  # noqa: E402
from crbm.train import train_model  # noqa: E402
from lacuna.modelfile import load_model  # noqa: E402
from mocap.protocols import get_protocol  # noqa: E402


class Ensemble:
    """Offline fill = the mean of the members' fills; reseeding gives each member its own seed."""

    def __init__(self, members: list) -> None:
        self.members = members

    def reseed(self, seed: int) -> None:
        for i, m in enumerate(self.members):
            m.reseed(seed * 100 + i)

    def fill_offline(self, frames: np.ndarray, observed: np.ndarray):
        return np.mean([m.fill_offline(frames, observed)[0] for m in self.members], 0), None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--epochs", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=3, help="stochastic fills averaged per case")
    ap.add_argument("--cache", default="bench/out/crbm-seeds")
    ap.add_argument("--json", dest="json_out")
    a = ap.parse_args()
    os.makedirs(a.cache, exist_ok=True)
    ts = get_protocol("taylor2007").training_set()
    base = baseline_scores()
    members, rows = [], {}
    for s in a.seeds:
        f = os.path.join(a.cache, f"crbm-imp-s{s}-e{a.epochs}.npz")
        if not os.path.exists(f):
            t0 = time.perf_counter()
            train_model(ts.sequences, ts.channels, seed=s, epochs=a.epochs, positive_hidden="prob", average_last=0.2,
                        n_chains=8, method="crbm-imp").save(f)
            print(f"seed {s}: trained in {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
        members.append(load_model(f))
        r = ratios(score_model(members[-1], repeats=a.repeats, seed=0), base)
        rows[f"seed {s}"] = {f"{k[0]} {k[1]}": round(v, 3) for k, v in r.items()}
        print(f"seed {s}: {rows[f'seed {s}']}", flush=True)
    if len(members) > 1:
        r = ratios(score_model(Ensemble(members), repeats=a.repeats, seed=0), base)
        rows[f"ensemble {a.seeds}"] = {f"{k[0]} {k[1]}": round(v, 3) for k, v in r.items()}
        print(f"ensemble of seeds {a.seeds}: {rows[f'ensemble {a.seeds}']}", flush=True)
    if a.json_out:
        with open(a.json_out, "w") as fh:
            json.dump({"epochs": a.epochs, "repeats": a.repeats, "ratios": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
