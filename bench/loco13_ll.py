"""loco-13's model files (bench/notebook/loco-13.md): a copy of a ``default`` model file per long_ll
setting (blend/withhlm.py, "long_ll"), for ``lacuna eval --model``.

    .venv/bin/python bench/loco13_ll.py bench/out/l13/dh_pan.npz --ll 4,30 [--ll 8,60 ...]

Writes IN_llD_TAU.npz per --ll (the file as given otherwise; the whole-body baseline), IN_llLD_TAU.npz with
``--legs`` (long_ll_legs: the legs-only baseline, bench/notebook/loco-14.md).
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lacuna.modelfile import load_model  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("--ll", action="append", default=[], help="D,TAU (nats a feature, frames)")
    ap.add_argument("--legs", action="store_true", help="with long_ll_legs (the legs-only baseline, loco-14): IN_llLD_TAU.npz")
    a = ap.parse_args(argv)
    import blend.methods  # noqa: F401  (loaders)

    for spec in a.ll:
        d, tau = (float(v) for v in spec.split(","))
        m = load_model(a.model)
        m.set_long_ll(d, tau)
        m.set_long_ll_legs(a.legs)
        out = f"{a.model[:-4]}_ll{'L' if a.legs else ''}{spec.replace(',', '_')}.npz"
        m.save(out)
        print("wrote", out, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
