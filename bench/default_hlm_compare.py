"""Side by side tables from ``lacuna eval --json`` files of the gaps protocol (bench/notebook/mixq-4.md):
per activity the figures ``default`` is judged on (RMS by gap length, by time since onset, calibration,
NLL, root position), then RMS per take; a cell where the first file is above the one named by
--against (hold) is marked.

    .venv/bin/python bench/default_hlm_compare.py after=A.json before=B.json blend=C.json hold=D.json --against hold
"""
from __future__ import annotations

import argparse
import json
import sys

ACTS = ("walk", "turn", "run", "nonloco")
METRICS = ["rms_deg"] + [f"rms_deg[len {b}]" for b in ("<0.1s", "0.1-0.25s", "0.25-0.5s", "0.5-1s", "1-2s", ">=2s")] + \
    [f"rms_deg[since {b}]" for b in ("first", "0-0.05s", "0.05-0.1s", "0.1-0.25s", "0.25-0.5s", "0.5-1s", "1-2s")] + \
    ["rms_deg[first 0.1s]", "within_1std", "within_2std", "nll_per_value", "root_pos_rms_cm"]


def load(path: str) -> dict:
    out: dict = {}
    for r in json.load(open(path))["results"]:
        key = (r["activity"], r["metric"]) if r["test"] == "all" else (r["test"], r["metric"])
        out[key] = r["value"]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("files", nargs="+", help="NAME=FILE.json (the first is the one marked)")
    ap.add_argument("--against", default="hold")
    a = ap.parse_args()
    names = [f.split("=", 1)[0] for f in a.files]
    data = [load(f.split("=", 1)[1]) for f in a.files]
    ref = data[names.index(a.against)] if a.against in names else None
    fmt = lambda v: "-" if v is None else f"{v:.3f}" if v < 1.5 else f"{v:.2f}"  # noqa: E731
    print("| metric | " + " | ".join(f"{act}: {' / '.join(names)}" for act in ACTS) + " |")
    print("|---" * (len(ACTS) + 1) + "|")
    worse = []
    for m in METRICS:
        cells = []
        for act in ACTS:
            vs = [d.get((act, m)) for d in data]
            cell = " / ".join(fmt(v) for v in vs)
            if ref is not None and m.startswith("rms") and vs[0] is not None and ref.get((act, m)) is not None \
                    and vs[0] > ref[(act, m)] + 1e-9:
                cell += f" **>{a.against}**"
                worse.append((act, m))
            cells.append(cell)
        if any(c.replace(" / ", "").replace("-", "") for c in cells):
            print(f"| {m} | " + " | ".join(cells) + " |")
    takes = sorted({k[0] for d in data for k in d if k[0] not in ACTS + ("all",)})
    print("\n| take | " + " | ".join(names) + f" | {names[0]}/{names[1] if len(names) > 1 else names[0]} |")
    print("|---" * (len(names) + 2) + "|")
    for t in takes:
        vs = [d.get((t, "rms_deg")) for d in data]
        mark = " >" + a.against if ref is not None and vs[0] is not None and vs[0] > ref.get((t, "rms_deg"), 1e9) else ""
        ratio = f"{vs[0] / vs[1]:.3f}" if len(vs) > 1 and vs[0] and vs[1] else "-"
        print(f"| {t} | " + " | ".join(fmt(v) for v in vs) + f" | {ratio} |{mark}")
    print(f"\n{names[0]} worse than {a.against}: {worse}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
