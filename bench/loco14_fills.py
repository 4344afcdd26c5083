"""loco-14's old-file check (bench/notebook/loco-14.md): fills and stds of a ``default`` model file on three
VALIDATION cases (walking_21 -> 49_19 erased but the legs from 30 frames after the seam, where long_ll revokes;
the gaps protocol's first case at seed 0; walking_20 under pan2009's pattern), with the compiled and the numpy
mixing, dumped for a byte comparison between two source trees (PYTHONPATH picks the tree).

    PYTHONPATH=/work/main .venv/bin/python bench/loco14_fills.py MODEL.npz /tmp/a.npz
    PYTHONPATH=. .venv/bin/python bench/loco14_fills.py MODEL.npz /tmp/b.npz
    .venv/bin/python -c "import numpy as np; a, b = np.load('/tmp/a.npz'), np.load('/tmp/b.npz'); \
        print(all(a[k].tobytes() == b[k].tobytes() for k in a.files) and sorted(a.files) == sorted(b.files))"
"""
import sys

import numpy as np

import blend.methods  # noqa: F401  (loaders)
from blend import withhlm
from lacuna.modelfile import load_model
from mocap import protocols, splits

m = load_model(sys.argv[1]); out = {}
print(withhlm.__file__, m.long_ll, getattr(m, 'long_ll_legs', None))
legs = np.isin(withhlm.group_index(list(m.channels)), withhlm.LEG_GROUPS)
def run(name, x, obs, compiled):
    m.compiled = compiled
    st = m.stream(); f = np.empty_like(x); s = np.empty_like(x)
    for t in range(len(x)):
        r = st.step(np.where(obs[t], x[t], np.nan), obs[t]); f[t], s[t] = r.frame, r.std
    out[f"{name}_{int(compiled)}_fill"], out[f"{name}_{int(compiled)}_std"] = f, s
    out[f"{name}_{int(compiled)}_rev"] = np.array([st.n_llrev])
w = np.array(splits.load_take('walking_21').frames)[:600]
n = np.array(splits.load_take('49_19').frames)[:900].copy()
pos = [j for j, c in enumerate(m.channels) if c.startswith('root.t')]
n[:, pos] += w[-1, pos] - n[0, pos]
x = np.concatenate([w, n]); obs = np.ones(x.shape, bool); obs[630:, ~legs] = False
case = next(iter(protocols.Gaps(seed=0, split='validation').cases()))
p = np.array(splits.load_take('walking_20').frames); po = np.ones(p.shape, bool); po[len(p)//2:, ~legs] = False
for c in (True, False):
    run('splice', x, obs, c); run('gaps', case.truth, case.observed, c); run('pan', p, po, c)
np.savez(sys.argv[2], **out); print({k: v.shape for k, v in out.items() if k.endswith('rev')}, [int(v[0]) for k, v in out.items() if k.endswith('rev')])
