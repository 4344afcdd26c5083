"""pan-11's candidates (bench/notebook/pan-11.md): ``default`` trained as a protocol's eval trains it,
saved once, then a copy per long-erasure trust setting (blend/withhlm.py, "Long erasures"), each
scored with ``lacuna eval --model FILE`` (the same fills as the in-process training: seeded).

    .venv/bin/python bench/pan11_long_trust.py --protocol pan2009|gaps --out bench/out/p11/dh_pan [--trust 120,1.5 ...]

Writes OUT.npz (as trained: since pan-11 with the shipped trust; the figures of pan-11 section 1 used
one trained before it, i.e. off) and OUT_K_QMAX.npz per --trust (`--trust 0,0`: off).
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys

from lacuna import registry
from lacuna.modelfile import load_model
from mocap.protocols import Gaps, Pan2009


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--protocol", choices=("pan2009", "gaps"), required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--trust", action="append", default=[], help="K,QMAX (frames, q+ bound)")
    a = ap.parse_args(argv)
    base = a.out + ".npz"
    if not os.path.exists(base):
        proto = Pan2009(split="validation") if a.protocol == "pan2009" else Gaps(split="validation")
        ts = proto.training_set()
        registry.get_method("default").train(ts, **proto.options).save(base)
        print("trained on", ts.names, flush=True)
    for t in a.trust:   # "0,0": the trust off
        k, q = t.split(",")
        m = load_model(base)
        m.set_long_trust(int(k), float(q))
        m.save(f"{a.out}_{k}_{q}.npz")
        print("wrote", f"{a.out}_{k}_{q}.npz", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
