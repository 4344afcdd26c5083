"""hands-42's prototype (bench/notebook/hands-42.md): bench/default_loao.py with the numpy mixing's HLM share set
to 0 on the hand channels.

    OPENBLAS_NUM_THREADS=1 LACUNA_NO_JIT=1 HANDS=1 LACUNA_DATA=../shared/data .venv/bin/python \\
        bench/notebook/hands42_proto.py --root . --models /tmp/loao --policy PA1:0.5:0.0953...:0:COLLECTION --validation
"""
import inspect
import os
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]

HAND_JOINTS = ("lhand", "lfingers", "lthumb", "rhand", "rfingers", "rthumb")
if os.environ.get("HANDS"):
    import numpy as np

    from blend import withhlm

    src = textwrap.dedent(inspect.getsource(withhlm.WithHLMModel._mix_numpy))
    assert src.count("    y = Df + w * diff\n") == 1
    src = src.replace("    y = Df + w * diff\n",
                      "    w = np.where(np.array([c.split('.')[0] in HAND_JOINTS for c in self.channels])[None, :], 0.0, w)\n"
                      "    y = Df + w * diff\n")
    ns = dict(vars(withhlm))
    ns["HAND_JOINTS"] = HAND_JOINTS
    ns["np"] = np
    exec(src, ns)  # noqa: S102 - a prototype of one line of the numpy mixing
    withhlm.WithHLMModel._mix_numpy = ns["_mix_numpy"]

import default_loao  # noqa: E402

if __name__ == "__main__":
    sys.exit(default_loao.main(sys.argv[1:]))
