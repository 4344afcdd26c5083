"""Two ``lacuna eval`` runs of the same protocol compared: every figure of the JSONs (``--json``)
as eval prints it (3 decimals), and the fills of the ``--fills`` directories (max |a - b| in
degrees over the erased values and over all values, per take).  For a change that moves the
fills by rounding (bench/notebook/hlm64-12.md: the HLM's float32 tables).

    .venv/bin/python bench/eval_fill_diff.py A.json A-fills/ B.json B-fills/
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def main(argv: list[str]) -> int:
    ja, fa, jb, fb = argv
    ra = {(r["test"], r["erased"], r["activity"], r["metric"]): r["value"] for r in json.load(open(ja))["results"]}
    rb = {(r["test"], r["erased"], r["activity"], r["metric"]): r["value"] for r in json.load(open(jb))["results"]}
    keys = sorted(set(ra) | set(rb), key=str)
    moved = [(k, ra.get(k), rb.get(k)) for k in keys
             if not (isinstance(ra.get(k), (int, float)) and isinstance(rb.get(k), (int, float))
                     and f"{ra[k]:.3f}" == f"{rb[k]:.3f}")
             and ra.get(k) != rb.get(k)]
    print(f"figures: {len(keys)}, differing at 3 decimals: {len(moved)}")
    for k, a, b in moved:
        print("  ", k, a, b)
    worst = 0.0
    for p in sorted(Path(fa).glob("*.npz")):
        a, b = np.load(p), np.load(Path(fb) / p.name)
        er = a["erased"].astype(bool)
        d = np.abs(a["fill"] - b["fill"])
        de = float(np.nanmax(d[er])) if er.any() else 0.0
        worst = max(worst, de)
        print(f"{p.stem:>22}: max |fill a - fill b| erased {de:.3g} deg, all {float(np.nanmax(d)):.3g}; "
              f"std erased {float(np.nanmax(np.abs(a['std'] - b['std'])[er])) if er.any() else 0.0:.3g}")
    print(f"worst over the takes (erased): {worst:.3g} deg")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
