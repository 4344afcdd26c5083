"""Where a take's root orientation jumps by more than 90 degrees of heading in one frame.

The root's Euler channels (CMU ASF, R = Rz Ry Rx) are turned into heading, pitch and roll
(mocap.rootrot, R = Ry(yaw) Rx(pitch) Rz(roll)); a performer cannot turn 90 degrees in 1/120 s,
so such a step is in the file, not in the motion.  Prints every take of mocap.splits with one,
and the Euler channels around it.

    LACUNA_DATA=../shared/data .venv/bin/python bench/root_flips.py [--around 3]

Found (2026-12-03, bench/notebook/heading-7.md): cmu_li's circles walking_22 (TRAIN, frame 348),
walking_23 (VALIDATION, 539) and walking_24 (TEST, 694), each where ry passes +-90.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lacuna.errors import DataError  # noqa: E402
from mocap import splits  # noqa: E402
from mocap.rootrot import _matrix_to_ypr, _rxyz_to_matrix, wrap180  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--around", type=int, default=3, help="frames printed either side of a jump")
    args = ap.parse_args()
    found = 0
    for take in sorted(splits.ACTIVITY):
        try:
            m = splits.load_take(take)
        except DataError:  # a take this data directory does not hold (35_18 is in cmu35_taylor only)
            continue
        ch = list(m.channels)
        if not all(c in ch for c in ("root.rx", "root.ry", "root.rz")):
            continue
        E = m.frames[:, [ch.index(c) for c in ("root.rx", "root.ry", "root.rz")]]
        yaw, pitch, roll = (np.rad2deg(a) for a in _matrix_to_ypr(_rxyz_to_matrix(*np.deg2rad(E).T)))
        jumps = np.flatnonzero(np.abs(wrap180(np.diff(yaw))) > 90.0) + 1
        for t in jumps:
            found += 1
            print(f"{take} ({splits.split_of(take)}, {splits.ACTIVITY[take]}): heading {yaw[t - 1]:.1f} -> {yaw[t]:.1f} "
                  f"at frame {t}")
            for u in range(max(t - args.around, 0), min(t + args.around + 1, len(yaw))):
                print(f"    {u:5d}  rx ry rz {E[u, 0]:7.1f} {E[u, 1]:7.1f} {E[u, 2]:7.1f}   "
                      f"heading {yaw[u]:7.1f} pitch {pitch[u]:5.1f} roll {roll[u]:5.1f}")
    print(f"{found} jump(s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
