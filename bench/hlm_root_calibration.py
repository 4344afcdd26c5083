"""Is the std of a missing root's ground position honest?  Share of ground-position errors within
1 and 2 reported std over the root dropouts of the VALIDATION takes (``bench/hlm_validation.py``'s
``gaps+root`` and ``legs-only`` cases, occlusion seed 0), per activity.

    .venv/bin/python bench/hlm_root_calibration.py MODEL.npz

The reported std is per axis (tx, tz get the same); the 2-D error is compared as |e| / sqrt(2).
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from hlm_validation import CM_PER_UNIT, make_cases  # noqa: E402

from lacuna.modelfile import load_model  # noqa: E402
from mocap import splits  # noqa: E402


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print(__doc__)
        return 2
    model = load_model(args[0])
    acc = defaultdict(list)
    for c in make_cases(splits.VALIDATION, 1):
        if c["kind"] == "gaps":
            continue
        ch = c["channels"]
        px, pz = ch.index("root.tx"), ch.index("root.tz")
        fill, sd = model.fill_offline(np.where(c["obs"], c["truth"], np.nan), c["obs"].copy())
        miss = ~c["obs"][:, px]
        e = np.hypot(fill[:, px] - c["truth"][:, px], fill[:, pz] - c["truth"][:, pz])[miss] / np.sqrt(2.0)
        acc[splits.ACTIVITY[c["take"]]].append(np.stack([e, sd[miss, px]], 1))
    print("activity | within 1 std | within 2 std | median error / std | median std (cm)")
    for a, v in acc.items():
        v = np.vstack(v)
        r = v[:, 0] / np.maximum(v[:, 1], 1e-12)
        print(f"{a} | {np.mean(r <= 1):.3f} | {np.mean(r <= 2):.3f} | {np.median(r):.2f} | "
              f"{np.median(v[:, 1]) * CM_PER_UNIT:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
