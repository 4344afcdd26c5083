"""A performer who walks and then runs: the HLM's fill of the run with and without a change of
style (``style_switch``).

CMU 35_30 (walk) followed by 35_25 (run), both arms missing throughout, through one online
stream of a pan2009 model; prints the arms' RMS error on each part and the style the filter
holds during the run, for style_switch 0 (the paper: one style per take) and 1e-3.

    .venv/bin/python bench/hlm_style_change.py [--model M.npz] [--json OUT.json]

Without --model it trains on the pan2009 training set first (about 15-30 s).
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import sys

import numpy as np

from lacuna.modelfile import load_model
from mocap.datasets import load_trial
from mocap.protocols import get_protocol

ARMS = ("lhumerus", "lradius", "lwrist", "rhumerus", "rradius", "rwrist")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model")
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args(argv)
    if args.model:
        model = load_model(args.model)
    else:
        from hlm.methods import train_model

        proto = get_protocol("pan2009")
        ts = proto.training_set()
        print("training on pan2009 ...", file=sys.stderr, flush=True)
        model = train_model(ts.sequences, ts.channels, ts.names, **proto.options)
    walk, run = load_trial("35_30"), load_trial("35_25")
    frames = np.concatenate([walk.frames[:, walk.index(model.channels)], run.frames[:, run.index(model.channels)]])
    T = walk.frames.shape[0]
    arms = np.array([c.split(".")[0] in ARMS for c in model.channels])
    obs = np.ones(frames.shape, bool)
    obs[:, arms] = False
    rows = []
    for h in (0.0, 1e-3):
        st = model.with_options(style_switch=h).stream()
        out, style = [], []
        for t in range(frames.shape[0]):
            f = st.step(np.where(obs[t], frames[t], np.nan), obs[t])
            out.append(f.frame)
            style.append(int(np.argmax(f.extras["style"])))
        d = (np.array(out)[:, arms] - frames[:, arms] + 180.0) % 360.0 - 180.0
        sty = np.array(style)
        row = {"style_switch": h, "walk_rms_deg": float(np.sqrt((d[:T] ** 2).mean())),
               "run_rms_deg": float(np.sqrt((d[T:] ** 2).mean())),
               "walk_style": int(np.bincount(sty[:T]).argmax()),
               "run_styles": np.bincount(sty[T:], minlength=model.params.n_styles).tolist()}
        rows.append(row)
        print(f"style_switch {h:g}: walk arms RMS {row['walk_rms_deg']:.2f} deg, run arms RMS {row['run_rms_deg']:.2f} deg; "
              f"walk style {row['walk_style']}, frames of the run in each style {row['run_styles']}")
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump({"walk": "35_30", "run": "35_25", "rows": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
