"""bench/hlm_cold_tick.py with the 64 streams at different phases, as live: stream i plays CMU
35_08 (left arm missing) from its own offset i T / 64, as clients.loadgen does, where
hlm_cold_tick gives every stream the same frame (one posterior support shared by all streams, so
the filter's tables a tick reads are one stream's).  Same driver (the daemon object's bundled
tick, messages built beforehand, collector frozen), same parts, A/B across trees in one run,
rounds alternating; also the support size k of the posterior per frame (``--support``: one tree,
in process, from the compiled step's own k), bench/notebook/hlm64-12.md.  ``HLM_COLD_BUSY=1`` in a
tree's environment (``--env NAME:HLM_COLD_BUSY=1``) spends the gap spinning instead of sleeping;
``HLM_COLD_GAP_MS`` gives a tree its own gap (a gap sweep in one run, names sharing a tree).

    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python bench/hlm_cold_spread.py --root new=. \\
        --root main=/work/wt-hlm12-main --model /tmp/lacuna-echo-vs-daemon/hlm-e9b3d79.npz --gap-ms 8 --rounds 4
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def support(model: str, frames_n: int) -> dict:
    """The posterior's support per stream-frame (states with non-zero mass after the update: the
    k the compiled step visits) and how many states hold at least a fraction eps of the largest
    mass, over 64 streams at spread offsets stepped by ``step_block``, in process (one tree)."""
    import numpy as np

    from bench.hlm_cold_tick import N, frames_of
    from lacuna.modelfile import load_model

    m = load_model(model)
    ch, frames = frames_of(model)
    T = len(frames)
    offsets = (np.arange(N) * (T // N)) % T
    obs = np.isfinite(frames)
    streams = [m.stream() for _ in range(N)]
    rows = np.array([s.slot for s in streams])
    eps = (0.0, 1e-200, 1e-100, 1e-60, 1e-30, 1e-16, 1e-12, 1e-10, 1e-8, 1e-6, 1e-4)
    got: dict[float, list[int]] = {e: [] for e in eps}
    for k in range(frames_n):
        idx = (offsets + k) % T
        f = np.where(obs[idx], frames[idx], 0.0).astype(np.float64)
        m.step_block(streams, f, obs[idx].copy(), None)
        if k < 20:
            continue
        P = m.pool.core["post"][rows].reshape(N, -1)
        top = P.max(1, keepdims=True)
        for e in eps:
            got[e].extend((P > e * top).sum(1).tolist() if e else (P != 0).sum(1).tolist())
    return {str(e): {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)), "max": int(max(v)),
                     "mean": float(np.mean(v))} for e, v in got.items()}


def main(argv: list[str] | None = None) -> int:
    """``--support FRAMES``: the support count here, in process; otherwise bench/hlm_cold_tick.py's
    A/B driver and child with the streams at their own phases (``--env``, HLM_COLD_BUSY and
    HLM_COLD_GAP_MS as the module doc says)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    sys.path.insert(0, str(ROOT))   # (the driver; the children it starts import their own tree)
    if "--support" in argv:
        ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
        ap.add_argument("--model", required=True)
        ap.add_argument("--support", type=int, required=True, metavar="FRAMES")
        args, _ = ap.parse_known_args(argv)
        print(json.dumps(support(args.model, args.support), indent=1))
        return 0
    from bench.hlm_cold_tick import main as tick_main

    return tick_main(argv, spread=True, prog="bench/hlm_cold_spread.py", description=__doc__)


if __name__ == "__main__":
    sys.exit(main())
