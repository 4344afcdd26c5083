"""Side by side with Taylor's released CRBM code, as run in Octave by the anchor in
``/work/shared/anchors/taylor-octave`` (README there; none of the released code is kept here).

The anchor differs from ``lacuna``'s taylor2007 protocol in two places that are not the model:

* its input: the 62 raw channels of ``cmu35WalkJog.mat`` (root position and Euler angles as
  captured, no unwrapping), constant channels (std <= 1e-6) dropped, z-scored with the plain
  population mean and std.  The faithful ``crbm`` models the same raw root
  (``crbm.released.RELEASED_INPUT``) but unwraps the angles, which changes rhand.rz only; the
  improved variants model the paper's body-centred root (section 4).
* its score: the cumulative scaled error divides by the plain variance of the training frames;
  the protocol divides angles by the variance about the circular mean.  They differ on rhand.rz
  only.  ``cumulative_scaled`` is that score, used for the released code's saved fills
  (``octave_fills``) and ours (``crbm.experiment.ANCHOR_METRIC``) alike.

This module runs our CRBM and our filler core on exactly the anchor's input, and loads a model
the anchor trained (its ``.mat``) into our filler, so each difference can be measured alone:
released weights + our fill = the anchor's figures means the fill procedure agrees; our training
on the anchor's input against the released training on it compares the training alone.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from crbm.model import CRBM
from mocap import datasets

# erased groups as the anchor's crbmfill.m names them (0-based raw channel ranges; constant ones
# are left out as there)
GROUPS = {"right-leg": np.arange(13, 20), "upper-body": np.arange(20, 62)}
TESTS = ("35_18", "35_29")          # columns of lblstest


def anchor_data(root: str | Path | None = None) -> dict[str, Any]:
    """The anchor's input: training sequences z-scored as train.m does, and the statistics."""
    import scipy.io

    root = Path(root or datasets.data_dir(required=True))
    S = scipy.io.loadmat(str(root / "cmu35_taylor" / "cmu35WalkJog.mat"))
    Y = np.asarray(S["Y"], dtype=np.float64)
    sd, mu = Y.std(0), Y.mean(0)
    keep = np.flatnonzero(sd > 1e-6)
    Z = (Y[:, keep] - mu[keep]) / sd[keep]
    lab = S["lbls"].argmax(1)
    seqs = [Z[lab == k] for k in range(S["lbls"].shape[1]) if (lab == k).any()]
    tl = S["lblstest"].argmax(1)
    tests = {name: np.asarray(S["Ytest"], dtype=np.float64)[tl == k] for k, name in enumerate(TESTS)}
    return {"sequences": seqs, "keep": keep, "mean": mu, "std": sd, "plain_var": Y.var(0), "tests": tests}


def cumulative_scaled(fill: np.ndarray, truth: np.ndarray, cols: np.ndarray, start: int, var: np.ndarray) -> float:
    """THE score, for the released code's fills and ours alike (crbmfill.m's last lines, 0-based
    ``start``): per erased raw channel in ``cols``, the squared error wrapped into [-180, 180)
    summed over frames ``start:``, divided by the channel's ``var``; the mean over channels.
    With ``var`` = the plain variance of the training frames (``std(Y, 1).^2``) this is the
    figure the issue quotes for the released code (8.3 / 12.1 on 35_29)."""
    cols = np.asarray(cols)
    e = (np.asarray(fill, np.float64)[start:, cols] - np.asarray(truth, np.float64)[start:, cols] + 180.0) % 360.0 - 180.0
    return float(np.mean(np.sum(e**2, 0) / np.asarray(var, np.float64)[cols]))


def octave_fills(path: str | Path, data: dict[str, Any] | None = None) -> dict[tuple[str, str], list[float]]:
    """Score the fills the anchor's Octave fill saved (``crbmfill_save.m``: a cell FILLS of
    structs seq, group, run, F (frames x kept channels, raw units), keep, miss, st, 1-based) with
    ``cumulative_scaled`` against the plain training variance: {(test, group): one score per run}."""
    import scipy.io

    data = data or anchor_data()
    cells = scipy.io.loadmat(str(path), simplify_cells=True)["FILLS"]
    out: dict[tuple[str, str], list[float]] = {}
    for c in cells:
        test, group = TESTS[int(c["seq"]) - 1], tuple(GROUPS)[int(c["group"]) - 1]
        X = data["tests"][test]
        keep = np.asarray(c["keep"]).ravel().astype(int) - 1
        full = X.copy()
        full[:, keep] = np.asarray(c["F"], np.float64)
        cols = keep[np.asarray(c["miss"]).ravel().astype(int) - 1]
        out.setdefault((test, group), []).append(cumulative_scaled(full, X, cols, int(c["st"]) - 1, data["plain_var"]))
    return out


def filler(crbm: CRBM):
    """Our filler over the anchor's z-scored channels (an identity representation)."""
    from crbm.filler import CRBMModel
    from mocap.representation import Representation

    F = crbm.n_visible_
    ch = [f"z{i}.tx" for i in range(F)]
    rep = Representation(ch, [True] * F, [0.0] * F, [0.0] * F, "raw", False, [0.0] * F, [1.0] * F, ch)
    return CRBMModel(rep, crbm)


def load_octave_model(path: str | Path) -> CRBM:
    """A model saved by the anchor's train.m (vishid, pastvis, pasthid, visbiases, hidbiases,
    component 1) as our CRBM.  The released code orders the past oldest first
    ``[v_{t-n} ... v_{t-1}]``; ours is newest first, so the row blocks of A and B are reversed."""
    import scipy.io

    M = scipy.io.loadmat(str(path))
    F = int(np.asarray(M["keep"]).size)
    n = int(np.asarray(M["nt"]).ravel()[0])
    W = np.asarray(M["vishid"], dtype=np.float64).reshape(F, -1)
    H = W.shape[1]
    A = np.asarray(M["pastvis"], dtype=np.float64).reshape(n * F, F)
    B = np.asarray(M["pasthid"], dtype=np.float64).reshape(n * F, H)
    rows = np.concatenate([np.arange((n - 1 - q) * F, (n - q) * F) for q in range(n)])
    c = CRBM(n_hidden=H, order=n)
    c.W_, c.A_, c.B_ = W, A[rows], B[rows]
    c.c_ = np.asarray(M["visbiases"], dtype=np.float64).ravel()[:F]
    c.b_ = np.asarray(M["hidbiases"], dtype=np.float64).ravel()[:H]
    c.n_visible_ = F
    c._rng = np.random.default_rng(0)
    return c


def score(crbm: CRBM, data: dict[str, Any], repeats: int = 10, circular_var: np.ndarray | None = None,
          seed: int = 0) -> dict[tuple[str, str], dict[str, float]]:
    """The anchor's crbmfill.m experiment with our filler: from the middle of each test take the
    group is erased and filled frame by frame (K = 30, one chain); the cumulative scaled error
    against the plain training variance (the anchor's figure) and, given ``circular_var`` (the
    protocol's per-channel variance), the protocol's; mean and std over ``repeats`` fills."""
    model = filler(crbm)
    keep, mu, sd = data["keep"], data["mean"], data["std"]
    out = {}
    for name, X in data["tests"].items():
        N = X.shape[0]
        st = N // 2
        Zt = (X[:, keep] - mu[keep]) / sd[keep]
        for g, cols in GROUPS.items():
            cols = cols[sd[cols] > 1e-6]
            miss = np.searchsorted(keep, cols)
            obs = np.ones(len(keep), bool)
            obs[miss] = False
            plain, circ = [], []
            full = X.copy()
            for r in range(repeats):
                model.reseed(seed + r)
                state = model.core_init(1)
                V = Zt.copy()
                for t in range(N):
                    o = obs if t >= st else np.ones(len(keep), bool)
                    V[t] = model.core_step(state, np.where(o, Zt[t], np.nan)[None], o[None]).z[0]
                full[:, keep] = V * sd[keep] + mu[keep]
                plain.append(cumulative_scaled(full, X, cols, st, data["plain_var"]))
                if circular_var is not None:
                    circ.append(cumulative_scaled(full, X, cols, st, circular_var))
            res = {"plain_var": float(np.mean(plain)), "plain_var std": float(np.std(plain))}
            if circ:
                res.update({"protocol": float(np.mean(circ)), "protocol std": float(np.std(circ))})
            out[(name, g)] = res
    return out
