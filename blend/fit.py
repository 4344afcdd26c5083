"""Fitting ``default``: the Gaussian on training takes, the stacking weights and the std scale on
held-out (VALIDATION) takes with simulated dropouts.

``occlusion`` erases joint groups (and the root) in bursts of 0.1-2 s like the gaps protocol,
with its own seeds; ``collect`` runs the causal stream over such takes and keeps, for every
erased value, the three components, the truth and the channel's spread; ``fit_weights`` solves
the stacking by least squares (each activity weighted by the inverse of its hold error, so
walks count as much as basketball) and sets the std scale per group and time since onset to
the 95% quantile of |error| / spread, divided by 1.96.
"""
from __future__ import annotations

import zlib
from collections.abc import Sequence

import numpy as np

from blend.model import GROUP_NAMES, GROUPS, NO_REGRESSION, ROOT_POS, DefaultModel, Settings, Weights, group_of, wrap
from mocap.protocols import erase_bursts
from mocap.representation import circular_mean_deg, is_angle

GAP_RANGE = (0.1, 2.0)
RATE = 0.6        # bursts per second per group
ROOT_RATE = 0.6   # the root drops out as often as a limb (as in the gaps protocol)
LEAD = 0.25


def fit_gaussian(sequences: Sequence[np.ndarray], channels: Sequence[str], settings: Settings):
    """mean, std (C,), reg_idx (R,), mu (nb R,), cov (nb R, nb R) over [pose deviation, change over each lag]."""
    X = np.vstack(sequences)
    ang = np.array([is_angle(c) for c in channels])
    mean = np.where(ang, circular_mean_deg(X), X.mean(0))
    dev = np.where(ang[None], wrap(X - mean), X - mean)
    std = np.sqrt(np.mean(dev**2, 0))
    reg = np.array([i for i, c in enumerate(channels) if ang[i] and group_of(c) not in NO_REGRESSION and std[i] > 1e-3], int)
    Ls = settings.per_frame()["L"]
    Lm = max(Ls)
    feats = []
    for s in sequences:
        if s.shape[0] <= Lm:
            continue
        x = s[Lm:, reg]
        parts = [wrap(x - mean[reg])] + [wrap(x - s[Lm - L:s.shape[0] - L, reg]) for L in Ls]
        feats.append(np.hstack(parts))
    Z = np.vstack(feats)
    mu = Z.mean(0)
    cov = np.cov(Z, rowvar=False)
    return mean, std, reg, mu, cov


def velocity_rms(sequences: Sequence[np.ndarray], channels: Sequence[str]) -> np.ndarray:
    """(C,) RMS change per frame of each channel over the takes (wrapped for angles)."""
    ang = np.array([is_angle(c) for c in channels])
    d = np.vstack([np.where(ang[None], wrap(np.diff(s, axis=0)), np.diff(s, axis=0)) for s in sequences if len(s) > 1])
    return np.sqrt(np.mean(d**2, 0)) + 1e-6


def velocity_gain(sequences: Sequence[np.ndarray], channels: Sequence[str], settings: Settings,
                  horizon_s: float = 0.1) -> np.ndarray:
    """(C,) least-squares gain of the damped velocity extrapolation over ``horizon_s`` on the takes,
    with the stream's own velocity filter; clipped to [0, 1]."""
    from scipy.signal import lfilter

    probe = DefaultModel(list(channels), np.zeros(len(channels)), np.ones(len(channels)), np.zeros(0, int),
                         np.zeros(0), np.zeros((0, 0)), settings, Weights.initial())
    ang = probe.ang
    d = probe._pf["d"]
    h = max(1, int(round(horizon_s * settings.fps)))
    D = d * (1 - d**h) / (1 - d)
    num = np.zeros(len(channels))
    den = np.zeros(len(channels))
    for s in sequences:
        if s.shape[0] <= h + 2:
            continue
        dx = np.where(ang[None], wrap(np.diff(s, axis=0)), np.diff(s, axis=0))
        v = np.empty_like(dx)
        for b in np.unique(probe.beta):
            cols = probe.beta == b
            v[:, cols] = lfilter([b], [1.0, -(1.0 - b)], dx[:, cols], axis=0)
        x = s[1:]
        y = np.where(ang[None], wrap(x[h:] - x[:-h]), x[h:] - x[:-h])
        u = v[:-h] * D
        num += (y * u).sum(0)
        den += (u * u).sum(0)
    return np.clip(num / np.maximum(den, 1e-12), 0.0, 1.0)


def occlusion(name: str, T: int, channels: Sequence[str], fps: float, seed: int, root: bool = True):
    """(T, C) observed mask and bursts [(group, start, stop)]."""
    rng = np.random.default_rng([seed, zlib.crc32(name.encode()), 7])
    obs = np.ones((T, len(channels)), bool)
    bursts = []
    grp = np.array([group_of(c) for c in channels])
    lo, hi = GAP_RANGE
    for gi, g in enumerate(GROUPS):
        if g == "root" and not root:
            continue
        rate = ROOT_RATE if g == "root" else RATE
        cols = (grp == gi) | ((gi == 0) & (grp == ROOT_POS))
        if not cols.any():
            continue
        erase_bursts(obs, cols, g, rng, fps, LEAD, rate, lo, hi, bursts)
    return obs, bursts


def collect(model: DefaultModel, takes: Sequence[tuple[str, np.ndarray, str]], seeds: Sequence[int]) -> dict[str, np.ndarray]:
    """Run the stream over (name, frames, activity) with occlusions; one row per erased value."""
    rows: dict[str, list] = {k: [] for k in ("k", "g", "H", "V", "W", "R", "amp", "gate", "weak", "lam", "lamr", "y", "act", "ch", "take")}
    acts = sorted({a for _, _, a in takes})
    for seed in seeds:
        for ti, (name, frames, act) in enumerate(takes):
            obs, _ = occlusion(name, frames.shape[0], model.channels, model.settings.fps, seed)
            st = model.stream()
            st.collect = True
            for t in range(frames.shape[0]):
                st.step(np.where(obs[t], frames[t], np.nan), obs[t])
                c = st.comp
                if c is None:
                    continue
                truth = frames[t, c.idx]
                H = c.H
                y = np.where(model.ang[c.idx], H + wrap(truth - H), truth)  # truth unwrapped near H
                rows["k"].append(c.k); rows["g"].append(model.group[c.idx]); rows["H"].append(H)
                rows["V"].append(c.V); rows["W"].append(c.W); rows["R"].append(c.R); rows["amp"].append(c.amp); rows["gate"].append(c.gate); rows["weak"].append(c.weak); rows["y"].append(y)
                rows["lam"].append(np.ones(len(c.idx)) if c.lam is None else c.lam)
                rows["lamr"].append(np.ones(len(c.idx)) if c.lamr is None else c.lamr)
                rows["act"].append(np.full(len(c.idx), acts.index(act))); rows["ch"].append(c.idx)
                rows["take"].append(np.full(len(c.idx), ti))
    out = {k: np.concatenate(v) if v else np.zeros(0) for k, v in rows.items()}
    out["activities"] = np.array(acts)
    return out


def _hat(model: DefaultModel, t: np.ndarray) -> np.ndarray:
    K = len(model.knots)
    p = np.interp(t, model.knots, np.arange(K, dtype=float))
    i = np.minimum(p.astype(int), K - 2)
    f = p - i
    Phi = np.zeros((len(t), K))
    Phi[np.arange(len(t)), i] = 1 - f
    Phi[np.arange(len(t)), i + 1] += f
    return Phi


CELL_EDGES = (0.0, 1.5 / 120, 0.05, 0.1, 0.25, 0.5, 1.0, 2.0, 1e9)  # seconds since onset: the cells kept <= hold
# (the first erased frame is a cell of its own)


def fit_weights(model: DefaultModel, data: dict[str, np.ndarray], ridge: float = 1e-2, smooth: float = 1.0,
                coverage: float = 0.95, rounds: int = 40, per_group: tuple = (0,), target: float = 1.0,
                unboosted: tuple = (ROOT_POS,)) -> Weights:
    """Stacking weights by weighted least squares; then, while some (activity, time since onset[,
    joint group]) cell has an MSE above ``target``^2 x hold's, that cell's values weigh more
    (up to ``rounds`` refits).  The groups in ``per_group`` (the root's angles: they were worse than
    hold on walks behind the others' gains) have cells of their own; the rest share (activity, time
    since onset) cells (cells per group for all of them cost a third of the gain over hold on 2
    folds of VALIDATION, bench/notebook/fill.md); the groups in ``unboosted`` (the root's
    translation, in length units, not degrees) are fitted but their cells never boosted (boosting
    them drove the root position back toward hold: 2-fold RMS/hold on walks 0.78 against 0.25);
    ``target`` < 1 leaves a margin for takes the weights never saw (chosen by 2 folds on VALIDATION,
    bench/default_cells.py)."""
    G, K = len(GROUP_NAMES), len(model.knots)
    t = data["k"] / model.settings.fps
    Phi = _hat(model, t)
    H = data["H"]
    dV, dW, dR, y = data["V"] - H, data["W"] - H, data["R"] - H, data["y"] - H
    if "lam" in data:  # the guard's scales of the velocity and regression parts, as the stream had them
        dV, dW, dR = dV * data["lam"], dW * data["lam"], dR * data["lamr"]
    dG = dR * data["gate"]
    dR = dR * data["weak"]
    sw = np.zeros(len(y))
    for a in np.unique(data["act"]):
        sel = data["act"] == a
        sw[sel] = 1.0 / max(np.mean(y[sel] ** 2), 1e-9) / sel.sum()
    cell = data["act"] * 100 + np.searchsorted(CELL_EDGES, t, side="right")
    own = np.isin(data["g"], np.asarray(per_group, int))
    cell = cell * 100 + np.where(own, data["g"] + 1, 0)
    cell = np.where(np.isin(data["g"], np.asarray(unboosted, int)), -1, cell)  # fitted, never boosted
    cells = np.unique(cell[cell >= 0])
    boost = np.ones(len(y))
    for _ in range(rounds):
        w = Weights.initial(G, K)
        for g in range(G):
            sel = data["g"] == g
            if sel.any():
                _solve(w, g, Phi[sel], dV[sel], dW[sel], dR[sel], dG[sel], y[sel], sw[sel] * boost[sel], ridge, smooth)
        gg = data["g"]
        fill = H + np.sum(Phi * (w.wv[gg] * dV[:, None] + w.wl[gg] * dW[:, None] + w.wr[gg] * dR[:, None]
                                 + w.wg[gg] * dG[:, None]), 1)
        e2, h2 = (data["y"] - fill) ** 2, y**2
        worst = 0.0
        for c in cells:
            sel = cell == c
            r = e2[sel].sum() / max(h2[sel].sum(), 1e-12)
            worst = max(worst, r)
            if r > target**2:
                boost[sel] *= (r / target**2) ** 8
        if worst <= target**2:
            break
    ratio = np.abs(data["y"] - fill) / np.maximum(data["amp"], 1e-9)
    w.sc[:] = _scale(ratio, data["g"], Phi, G, K, coverage)
    return w


def _solve(w: Weights, g: int, Phi, dV, dW, dR, dG, y, sw, ridge, smooth) -> None:
    K = Phi.shape[1]
    feats = [Phi * dV[:, None], Phi * dW[:, None]]
    if g not in NO_REGRESSION:
        feats += [Phi * dR[:, None], Phi * dG[:, None]]
    A = np.hstack(feats)
    s = np.sqrt(sw)
    As, ys = A * s[:, None], y * s
    AtA = As.T @ As
    # ridge towards hold, plus a penalty on second differences across knots (no steps in a gap)
    D = np.diff(np.eye(K), 2, axis=0)
    P = np.kron(np.eye(len(feats)), D.T @ D)
    scale = np.trace(AtA) / A.shape[1] + 1e-12
    coef = np.linalg.solve(AtA + scale * (ridge * np.eye(A.shape[1]) + smooth * P), As.T @ ys)
    w.wv[g], w.wl[g] = coef[:K], coef[K:2 * K]
    if g not in NO_REGRESSION:
        w.wr[g], w.wg[g] = coef[2 * K:3 * K], coef[3 * K:]


def _scale(ratio, g, Phi, G, K, coverage):
    """Per group and knot: the coverage quantile of ratio / 1.96 among the values nearest that knot."""
    near = Phi.argmax(1)
    z = 1.959964 if abs(coverage - 0.95) < 1e-9 else float(np.sqrt(2) * _erfinv(coverage))
    sc = np.ones((G, K))
    allq = np.quantile(ratio, coverage) / z if len(ratio) else 1.0
    for gi in range(G):
        for k in range(K):
            sel = (g == gi) & (near == k)
            sc[gi, k] = np.quantile(ratio[sel], coverage) / z if sel.sum() >= 50 else np.nan
        row = sc[gi]
        ok = np.isfinite(row)
        sc[gi] = np.interp(np.arange(K), np.flatnonzero(ok), row[ok]) if ok.any() else allq
    return sc


def _erfinv(p: float) -> float:
    from scipy.special import erfinv

    return float(erfinv(p))
