"""hclip-42's prototype (bench/notebook/hclip-42.md): bench/default_loao.py with the numpy mixing's
``y = D + w (H - D)`` replaced by ``y = D + w clip(H - D, -k sD, k sD)``; not in the code (the rule failed).

    OPENBLAS_NUM_THREADS=1 LACUNA_NO_JIT=1 HCLIP=2 LACUNA_DATA=../shared/data .venv/bin/python \\
        bench/notebook/hclip42_proto.py --root . --models /tmp/loao --policy PA1:0.5:0.0953...:0:COLLECTION --validation
"""
import inspect
import os
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]

KC = float(os.environ.get("HCLIP", "0"))
if KC > 0:
    from blend import withhlm

    src = textwrap.dedent(inspect.getsource(withhlm.WithHLMModel._mix_numpy))
    assert src.count("    y = Df + w * diff\n") == 1
    src = src.replace("    y = Df + w * diff\n", "    y = Df + w * np.clip(diff, -KC * Dsd, KC * Dsd)\n")
    ns = dict(vars(withhlm))
    ns["KC"] = KC
    exec(src, ns)  # noqa: S102 - a prototype of one line of the numpy mixing
    withhlm.WithHLMModel._mix_numpy = ns["_mix_numpy"]

import default_loao  # noqa: E402

if __name__ == "__main__":
    sys.exit(default_loao.main(sys.argv[1:]))
