"""The compiled mixing's call cost with the band's extras (blend/withhlm.py "Rate", "Band q"),
alternated in one process, 62 channels: another tree's ``mix_row`` (``--main``), this tree's with the
extras off (the kernels not called), and this tree's with one on: ``--on rate`` (band-12: ``mix_row``
then ``rate_band``) or ``--on q`` (band-13: ``mix_row`` then ``q_band`` with its rate gate, which updates
the rate sums itself).  Writes nothing into either tree (numba's caches in a scratch directory).

    OPENBLAS_NUM_THREADS=1 nice -n 19 .venv/bin/python bench/band_mixcost.py --main /work/main --on q
"""
import argparse
import importlib.util
import os
import sys
import tempfile
import time
from pathlib import Path

# numba's on-disk caches go to a scratch directory, never beside the other tree's sources (a read-only
# tree for this bench), and python writes no bytecode there either
os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="band-mixcost-")
sys.dont_write_bytecode = True

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from blend import withhlm  # noqa: E402
from blend.withhlm_fast import mix_row as new  # noqa: E402
from blend.withhlm_fast import q_band, rate_band  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("--main", default="/work/main")
ap.add_argument("--on", choices=["rate", "q"], default="q", help="which extra the 'on' row runs")
args = ap.parse_args()
spec = importlib.util.spec_from_file_location("main_fast", str(Path(args.main) / "blend/withhlm_fast.py"))
assert spec is not None and spec.loader is not None
mf = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mf)
old = mf.mix_row
C = 62
rng = np.random.default_rng(0)
F = rng.normal(size=C)
O = rng.random(C) > 0.3
HO = O.copy()
D, Dsd, H, Hsd = (rng.normal(size=C) for _ in range(4))
Dsd, Hsd = abs(Dsd), abs(Hsd)
ang = np.ones(C, bool)
grp = np.arange(C)
TB = len(withhlm.T_EDGES) + 1
W = np.full((C, TB, 4), 0.5)
S = np.ones((C, TB))
k = np.zeros(C, np.int64)
o = np.zeros(C)
out = np.empty(C)
std = np.empty(C)
kn = withhlm.T_KNOTS.copy()
rp, vp, e, wb = (np.zeros(C) for _ in range(4))
ref = np.ones(C)
rst = np.zeros((4, C))
rst[0], rst[1] = rng.random(C) * 10, 8.0   # every channel with history: the median over all 62
kM = np.full((C, 4), 0.6)
mb, buf = np.ones(C), np.zeros(C)
gpar = np.array([1.6, 1.8, 1.0])
rpar_on = np.array([0.99, 1.0, 0.5, 2.0])   # decay, a 1, clip 0.5-2 (still channels' sums flush to 0: _ftz)


def a():
    old(F, O, HO, D, Dsd, H, Hsd, D, False, ang, grp, W, S, withhlm.T_EDGES, 0, 0.97, k, o, out, std, kn, False, 2.0, 1.0, 0.7, rp, vp, e, 0.92, wb)


def b():
    new(F, O, HO, D, Dsd, H, Hsd, D, False, ang, grp, W, S, withhlm.T_EDGES, 0, 0.97, k, o, out, std, kn, False, 2.0, 1.0, 0.7, rp, vp, e, 0.92, wb)


def c():
    b()
    if args.on == "rate":
        rate_band(F, O, ang, std, rpar_on, ref, rst)
    else:   # decay 1: the history of the still frames stays as it is (every channel keeps a rate)
        q_band(F, O, ang, std, k, kM, 0, 0.92, mb, gpar, ref, rst, 1.0, True, buf)


a()
b()
c()
res: dict[str, list[float]] = {"main": [], "off": [], "on": []}
order = [("main", a), ("off", b), ("on", c)]
for r in range(21):
    for name, f in order[r % 3:] + order[:r % 3]:
        t0 = time.perf_counter()
        for _ in range(20000):
            f()
        res[name].append((time.perf_counter() - t0) / 20000 * 1e6)
med = {n: float(np.median(v)) for n, v in res.items()}
print("mix_row us/call (median of 21 x 20,000): " + ", ".join(f"{n} {v:.2f}" for n, v in med.items())
      + f"; off / main {med['off'] / med['main']:.3f}, on / main {med['on'] / med['main']:.3f}")
