"""Stage-by-stage replay of Taylor's released CRBM code against ours, on the same random numbers.

Octave runs the released training (``mixgaussiancrbm.m`` of github:gwtaylor/imCRBM, one
component, as ``/work/shared/anchors/taylor-octave/train.m`` drives it) and the anchor's fill
(``crbmfill.m``) with ``randn`` and ``rand`` shadowed by functions that record every draw
(``OCTAVE_RANDN``, ``OCTAVE_RAND``); nothing of the released code is kept here, the caller
points at a directory holding it.  Ours then runs on the recorded draws:

* training (``replay_training``): the initial weights are the first five ``randn`` draws
  (vishid, visbiases, hidbiases, pastvis, pasthid, each ``single(0.01 * randn(...))``, lines
  "Randomly initialize weights"), the mini-batches the dump's ``MB``, then per mini-batch three
  ``randn`` blocks of history noise (``for hh = nt:-1:1``: frames t-3, t-2, t-1, "past = ...
  + randn") and one ``rand`` for the hidden states ("hidstates = single(poshidprobs > rand)").
  Our history is newest first, so the noise blocks and the rows of A and B are reversed.
* fill (``replay_fill``): per filled frame one ``randn(1, F)`` (the previous frame + 0.01 noise)
  and 30 ``rand(1, H)`` (the Gibbs iterations' hidden states); ours draws h = [a > L] with
  L = logit(u), which is h = [logistic(a) > u].

* the whole run (``train_on_streams``): ``OCTAVE_STREAMS`` regenerates every number the released
  training draws for a seed, without training; ours trains 2000 epochs on them and lands on the
  released code's own model of that seed (bench/crbm_released_draws.py).

Used by tests/test_crbm_faithful_replay.py, bench/crbm_released_draws.py and
bench/notebook/crbmleg.md.
"""
from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import numpy as np

from crbm import anchor
from crbm.model import CRBM
from crbm.released import RELEASED

RELEASED_FILES = ("mixgaussiancrbm.m", "crbmfe.m")

OCTAVE_RANDN = """function r = randn(varargin)
  % records every draw (replayed in Python by crbm.replay); seeding calls pass through
  global RECN
  if nargin >= 1 && ischar(varargin{1})
    builtin('randn', varargin{:}); r = []; return
  end
  r = builtin('randn', varargin{:}); RECN{end+1} = r;
end
"""
OCTAVE_RAND = OCTAVE_RANDN.replace("randn", "rand").replace("RECN", "RECU")
OCTAVE_SAMPLE_VECTOR = """function s = sample_vector(p)
  % single-component stand-in (the anchor's): every case takes component 1
  s = ones(1, size(p,2));
end
"""
# the anchor's train.m with SEED, EPOCHS and the recorded draws saved
OCTAVE_TRAIN = """more off; global RECN RECU; RECN = {}; RECU = {};
sd0 = str2double(getenv('SEED')); rand('seed', sd0); randn('seed', sd0);
S = load([getenv('DATA') '/cmu35_taylor/cmu35WalkJog.mat']);
Y = S.Y; lbls = S.lbls;
sd = std(Y,1); keep = find(sd > 1e-6); mu = mean(Y);
Z = (Y(:,keep) - mu(keep)) ./ sd(keep);
nt = 3; [~, seq] = max(lbls, [], 2);
valid = [];
for i = nt+1:size(Z,1)
  if all(seq(i-nt:i-1) == seq(i)), valid(end+1) = i; end
end
valid = valid(randperm(numel(valid)));
batchsize = 100; nb = floor(numel(valid)/batchsize);
minibatch = cell(nb,1);
for b=1:nb, minibatch{b} = valid((b-1)*batchsize+1 : b*batchsize); end
batchdata = single(Z);
numhid = str2double(getenv('NUMHID')); numcomp = 1; cdsteps = 1; gsd = 1; restart = 1;
numepochs = str2double(getenv('EPOCHS')); snapshotevery = 1e9; snapshot_path = [pwd '/snap'];
mixgaussiancrbm;
MB = cell2mat(minibatch);
save('-v7', getenv('OUT'), 'vishid','pastvis','pasthid','hidbiases','visbiases','mu','sd','keep','nt','MB','RECN','RECU','Z');
"""
# the anchor's crbmfill.m inner loop for one take (SEQ), one group (GROUP), FRAMES frames, run 1;
# STEPS holds the missing values at the start (1), after each Gibbs iteration (2..31) and after
# the final mean-field step (32)
OCTAVE_FILL = """more off; global RECN RECU; RECN = {}; RECU = {};
M = load(getenv('MODEL')); S = load([getenv('DATA') '/cmu35_taylor/cmu35WalkJog.mat']);
W = double(M.vishid(:,:,1)); A = double(M.pastvis(:,:,1)); B = double(M.pasthid(:,:,1));
bv = double(M.visbiases(1,:)); bh = double(M.hidbiases(1,:)); keep = M.keep; mu = M.mu; sd = M.sd; nt = M.nt;
s = str2double(getenv('SEQ')); g = str2double(getenv('GROUP')); nf = str2double(getenv('FRAMES'));
X = S.Ytest(S.lblstest(:,s)==1, :); N = size(X,1); st = floor(N/2) + 1;
Zt = (X(:,keep) - mu(keep)) ./ sd(keep);
groups = {'right-leg', 14:20; 'upper-body', 21:62};
missA = groups{g,2}; missA = missA(sd(missA) > 1e-6);
[~, miss] = ismember(missA, keep); obs = setdiff(1:numel(keep), miss);
randn('seed', 1); rand('seed', 1);
V = Zt; V(st:end, miss) = 0; STEPS = zeros(nf, 32, numel(miss));
for tt = st:st+nf-1
  v = V(tt-1,:) + 0.01*randn(1,numel(keep)); v(obs) = Zt(tt,obs); STEPS(tt-st+1, 1, :) = v(miss);
  past = reshape(V(tt-nt:tt-1,:)', 1, []);
  ev = bv + past*A; eh = bh + past*B;
  for gg = 1:30
    hp = 1./(1+exp(-(v*W + eh))); h = double(hp > rand(size(hp)));
    vm = h*W' + ev; v(miss) = vm(miss); STEPS(tt-st+1, gg+1, :) = v(miss);
  end
  hp = 1./(1+exp(-(v*W + eh))); vm = hp*W' + ev; v(miss) = vm(miss); STEPS(tt-st+1, 32, :) = v(miss);
  V(tt,:) = v;
end
F = V(1:st+nf-1, :);
save('-v7', getenv('OUT'), 'F', 'STEPS', 'RECN', 'RECU', 'st', 'miss', 'keep');
"""

# every random number train.m + mixgaussiancrbm.m draw for SEED over EPOCHS epochs, regenerated
# without training (the old generators' rand and randn streams are separate and fill matrices in
# order, so one long call equals the sequence of the released code's calls): the permutation of
# the valid frames, the initial weights (vishid, visbiases, hidbiases, pastvis, pasthid, in that
# order), then per mini-batch 3 x 100 x F normals and 100 x H uniforms, written as float32
OCTAVE_STREAMS = """more off; s = str2double(getenv('SEED')); E = str2double(getenv('EPOCHS')); rand('seed', s); randn('seed', s);
S = load([getenv('DATA') '/cmu35_taylor/cmu35WalkJog.mat']); sd = std(S.Y,1); F = sum(sd > 1e-6);
H = str2double(getenv('NUMHID')); [~, seq] = max(S.lbls, [], 2); nt = 3; valid = [];
for i = nt+1:size(S.Y,1)
  if all(seq(i-nt:i-1) == seq(i)), valid(end+1) = i; end
end
valid = valid(randperm(numel(valid))); nb = floor(numel(valid)/100);
MB = reshape(valid(1:nb*100), 100, nb)';
init = randn(F*H + F + H + nt*F*F + nt*F*H, 1);
save('-v7', [getenv('OUT') '.mat'], 'MB', 'init', 'F', 'H', 'nt', 'E');
fn = fopen([getenv('OUT') '.normals.f32'], 'w'); fu = fopen([getenv('OUT') '.uniforms.f32'], 'w');
for e = 1:E
  fwrite(fn, single(randn(nt*100*F*nb, 1)), 'single'); fwrite(fu, single(rand(100*H*nb, 1)), 'single');
end
fclose(fn); fclose(fu);
"""


class _Streams:
    """The regenerated streams of ``OCTAVE_STREAMS`` (memory-mapped), in our layout."""

    def __init__(self, prefix: str | Path, F: int, H: int, n: int):
        self._N = np.memmap(f"{prefix}.normals.f32", np.float32, "r")
        self._U = np.memmap(f"{prefix}.uniforms.f32", np.float32, "r")
        self._F, self._H, self._n, self._i, self._j = F, H, n, 0, 0

    def standard_normal(self, shape: tuple[int, ...]) -> np.ndarray:
        F, n, m = self._F, self._n, shape[0]
        a = np.asarray(self._N[self._i : self._i + n * m * F], np.float64).reshape(n, F, m).transpose(0, 2, 1)
        self._i += n * m * F
        return np.concatenate(list(a[::-1]), axis=1)     # t-3, t-2, t-1 -> newest first

    def random(self, shape: tuple[int, ...]) -> np.ndarray:
        m, H = shape
        a = np.asarray(self._U[self._j : self._j + m * H], np.float64).reshape(H, m).T
        self._j += m * H
        return a


def train_on_streams(prefix: str | Path, sequences: list[np.ndarray], progress=None) -> CRBM:
    """Our faithful training (crbm.released.RELEASED) on the released code's own random numbers
    for its whole run (``OCTAVE_STREAMS``'s files at ``prefix``); float64 parameters, as ``fit``."""
    meta = _load(f"{prefix}.mat")
    F, H, n, E = (int(meta[k]) for k in ("F", "H", "nt", "E"))
    init = np.asarray(meta["init"], np.float64).ravel()
    ours = CRBM(n_hidden=H, order=n, progress=progress, **RELEASED)
    ours._init(F)
    at = 0

    def take(rows: int, cols: int) -> np.ndarray:     # single(0.01 * randn(rows, cols)), column-major
        nonlocal at
        a = init[at : at + rows * cols]
        at += rows * cols
        return np.asarray(0.01 * a, np.float32).astype(np.float64).reshape(cols, rows).T

    rev = _reverse_blocks(n, F)
    ours.W_, ours.c_, ours.b_ = take(F, H), take(1, F).ravel(), take(1, H).ravel()
    ours.A_, ours.B_ = take(n * F, F)[rev], take(n * F, H)[rev]
    ours._as_dtype()
    ours._inc = {k: np.zeros_like(getattr(ours, k)) for k in ours._inc}
    _, idx = ours._stack(sequences)
    ours._batches, ours._batch_cases = list(np.atleast_2d(np.asarray(meta["MB"])).astype(int) - 1), idx
    ours._rng = _Streams(prefix, F, H, n)
    for _ in range(E):
        ours.partial_fit(sequences)
    for k in ("W_", "A_", "B_", "c_", "b_"):
        setattr(ours, k, getattr(ours, k).astype(np.float64))
    return ours


def released_dir() -> Path | None:
    """Where the released code's files are (``$LACUNA_IMCRBM``), or None when absent."""
    d = os.environ.get("LACUNA_IMCRBM")
    if d and all((Path(d) / f).is_file() for f in RELEASED_FILES):
        return Path(d)
    return None


def run_octave(work: Path, script: str, text: str, env: dict[str, str], released: Path) -> None:
    """Write the recording shims and ``script`` into ``work`` beside the released files; run it."""
    work.mkdir(parents=True, exist_ok=True)
    for f in RELEASED_FILES:
        shutil.copy(released / f, work / f)
    for name, body in (("randn.m", OCTAVE_RANDN), ("rand.m", OCTAVE_RAND), ("sample_vector.m", OCTAVE_SAMPLE_VECTOR),
                       ("visualize_mit.m", ""), (script, text)):
        (work / name).write_text(body)
    subprocess.run(["octave", "--no-gui", "-q", script], cwd=work, env={**os.environ, **env}, check=True,
                   capture_output=True, timeout=600)


def _load(path: str | Path) -> dict[str, Any]:
    import scipy.io

    return scipy.io.loadmat(str(path), simplify_cells=True)


class _Recorded:
    """Hands our training the released code's draws, in its order, in our layout."""

    def __init__(self, normals: list, uniforms: list):
        self._n, self._u = normals, uniforms
        self._i, self._j = 0, 0

    def standard_normal(self, shape: tuple[int, ...]) -> np.ndarray:
        blocks = self._n[self._i : self._i + 3]        # frames t-3, t-2, t-1 (oldest first)
        self._i += 3
        out = np.concatenate([np.atleast_2d(b) for b in blocks[::-1]], axis=1)   # ours: newest first
        assert out.shape == tuple(shape), (out.shape, shape)
        return out

    def random(self, shape: tuple[int, ...]) -> np.ndarray:
        out = np.atleast_2d(self._u[self._j])
        self._j += 1
        assert out.shape == tuple(shape), (out.shape, shape)
        return out


def _reverse_blocks(n: int, F: int) -> np.ndarray:
    return np.concatenate([np.arange((n - 1 - q) * F, (n - q) * F) for q in range(n)])


def replay_training(dump: str | Path, sequences: list[np.ndarray]) -> tuple[CRBM, CRBM, dict[str, Any]]:
    """Our CRBM (the faithful training, crbm.released.RELEASED) run on the dump's initial weights,
    mini-batches and draws for the dump's epochs; returns (ours, the released code's result, dump)."""
    M = _load(dump)
    RN, RU = list(M["RECN"]), list(M["RECU"])
    MB = np.atleast_2d(np.asarray(M["MB"])).astype(int) - 1
    F = int(np.asarray(M["keep"]).size)
    n = int(np.asarray(M["nt"]).ravel()[0])
    H = np.atleast_2d(RN[0]).shape[1]
    ours = CRBM(n_hidden=H, order=n, **RELEASED)
    ours._init(F)
    f32 = lambda a: np.asarray(0.01 * np.asarray(a, np.float64), np.float32).astype(np.float64).reshape(-1)  # noqa: E731
    rows = _reverse_blocks(n, F)
    ours.W_ = f32(RN[0]).reshape(F, H)
    ours.c_, ours.b_ = f32(RN[1]), f32(RN[2])
    ours.A_ = f32(RN[3]).reshape(n * F, F)[rows]
    ours.B_ = f32(RN[4]).reshape(n * F, H)[rows]
    _, idx = ours._stack(sequences)
    ours._batches, ours._batch_cases = list(MB), idx
    epochs = (len(RN) - 5) // 3 // len(MB)
    ours._rng = _Recorded(RN[5:], RU)
    for _ in range(epochs):
        ours.partial_fit(sequences)
    return ours, anchor.load_octave_model(dump), M


def replay_fill(model_dump: str | Path, fill_dump: str | Path, test: str = "35_29") -> tuple[np.ndarray, np.ndarray]:
    """Our filler (``crbm.anchor.filler``, the faithful fill) on the released weights and the fill
    dump's draws.  Returns (ours, theirs): the missing values of each filled frame, (frames, miss)."""
    M = _load(fill_dump)
    RN, RU = list(M["RECN"]), list(M["RECU"])
    model = anchor.filler(anchor.load_octave_model(model_dump))
    K = model.n_gibbs
    frame = iter(range(len(RN)))

    def draws(counts: np.ndarray, S: int, H: int, kn: object = None) -> tuple[np.ndarray, np.ndarray, None]:
        i = next(frame)
        u = np.stack([np.asarray(RU[i * K + k], np.float64).reshape(1, -1) for k in range(K)])
        return np.asarray(RN[i], np.float64).reshape(1, -1), np.log(u) - np.log1p(-u), None

    model._draws = draws     # the dump's numbers in place of the filler's own generator
    data = anchor.anchor_data()
    X = data["tests"][test]
    keep, mu, sd = data["keep"], data["mean"], data["std"]
    Zt = (X[:, keep] - mu[keep]) / sd[keep]
    st, miss = int(M["st"]) - 1, np.atleast_1d(np.asarray(M["miss"])).astype(int) - 1
    obs = np.ones(len(keep), bool)
    obs[miss] = False
    state, V = model.core_init(1), []
    for t in range(st + len(RN)):
        o = obs if t >= st else np.ones(len(keep), bool)
        V.append(model.core_step(state, np.where(o, Zt[t], np.nan)[None], o[None]).z[0])
    return np.asarray(V)[st:, miss], np.asarray(M["F"])[st:, miss]
