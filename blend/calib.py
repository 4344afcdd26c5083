"""Per-channel calibration of ``default``'s reported std (issue 17: "its std must be calibrated").

``default`` (blend/withhlm.py) reports std = S[g, bin(k)] sqrt(var) with S fitted per joint
group x time since onset.  Within a group the channels differ: the root's rotations come out far
too narrow (root.rz std / RMS 0.27 on VALIDATION), channels the training held still get a band
near 0, others too wide, so a studio looking at one joint's band sees a lie the activity totals
hide.  This module fits a factor per channel x time-since-onset bin,

    std' = F[c, bin(k)] std,      log F[c, t] = a_c + b_{g(c), t}

on VALIDATION only (bench/default_calib.py), from z = |truth - fill| / std of every erased value:

- a_g = log(q95(z over group g) / 2), the group's factor: 2 std' hold 95% of the group's errors;
- a_c = (n_c log(q95(z over c) / 2) + N0 a_g) / (n_c + N0): the channel's own factor shrunk toward
  its group's, n_c the channel's erased values; N0 chosen by leaving one VALIDATION take out at a
  time (bench/default_calib.py), so a channel with few erased values is not fitted to noise;
- with ``each`` (chosen by leaving one take out too), every q95 above is at least the ``each``
  quantile of each activity's z in the cell (a band has to hold in every activity, not on average);
- b_{g,t} the same on z / exp(a_c) per group x time bin, shrunk toward 0 with N1 (N1 = inf: no
  time-bin part), also chosen by leaving one take out;
- d_{c,t} the same on z / exp(a_c + b) per channel x time bin, shrunk toward 0 with N2 (a channel
  whose band is right at one horizon and wrong at another: the root's heading is too wide over
  short gaps and too narrow over seconds), chosen the same way; log F = a_c + b_{g,t} + d_{c,t}.

Only std changes: fills are the same to the bit (tests/test_default_calib.py).  A model file without
the array loads with F = 1.  Factors are stored by channel name in blend/withhlm.json ("calib"), so
``train_model`` gives a model of another skeleton the factors of its channels' groups (a_g + b) and
1 where the group is not known either.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

Q = 0.95                 # the share 2 std' should hold
TARGET = 2.0             # ... within this many std
MIN_GROUP = 200          # values a group (or group x time bin) needs for its own factor; fewer: 1
F_MIN, F_MAX = 0.05, 20.0


def _lq(z: np.ndarray, act: np.ndarray | None = None, each: float | None = None) -> float:
    """log of the factor that makes TARGET std hold a share Q of z and, with ``each``, at least a
    share ``each`` of every activity's z (activities with MIN_GROUP values)."""
    q = float(np.quantile(z, Q))
    if each is not None and act is not None:
        for a in np.unique(act):
            m = act == a
            if m.sum() >= MIN_GROUP:
                q = max(q, float(np.quantile(z[m], each)))
    return math.log(max(q, 1e-9) / TARGET)


def fit(z: np.ndarray, chan: np.ndarray, group: np.ndarray, tb: np.ndarray, n_ch: int, n_tb: int,
        n0: float, n1: float, act: np.ndarray | None = None, each: float | None = None,
        n2: float = math.inf) -> np.ndarray:
    """F (n_ch, n_tb) from the erased values' z = |error| / std, their channel, group, time bin
    (module doc).  ``group`` is per value; channels with no value get their group's factor."""
    G = int(group.max()) + 1 if len(group) else 0
    ag = np.zeros(max(G, 1))
    for g in range(G):
        m = group == g
        if m.sum() >= MIN_GROUP:
            ag[g] = _lq(z[m], None if act is None else act[m], each)
    gch = np.full(n_ch, -1)
    gch[chan] = group
    a = np.zeros(n_ch)
    for c in range(n_ch):
        g = gch[c]
        if g < 0:
            continue
        m = chan == c
        n = int(m.sum())
        if n and not np.any(z[m] > 1e-9):
            n = 0   # never off on VALIDATION (a channel held still everywhere): no evidence, the group's
        if n == 0 or not math.isfinite(n0):
            a[c] = ag[g]
        else:
            a[c] = (n * _lq(z[m], None if act is None else act[m], each) + n0 * ag[g]) / (n + n0)
    b = np.zeros((max(G, 1), n_tb))
    if math.isfinite(n1):
        r = z / np.exp(a[chan])
        for g in range(G):
            for t in range(n_tb):
                m = (group == g) & (tb == t)
                n = int(m.sum())
                if n >= MIN_GROUP:
                    b[g, t] = n * _lq(r[m], None if act is None else act[m], each) / (n + n1)
    L = a[:, None] + np.where(gch[:, None] >= 0, b[np.maximum(gch, 0)], 0.0)
    if math.isfinite(n2):
        r = z / np.exp(L[chan, tb])
        for c in range(n_ch):
            mc = chan == c
            if not mc.any() or not np.any(z[mc] > 1e-9):
                continue
            for t in range(n_tb):
                m = mc & (tb == t)
                n = int(m.sum())
                if n >= MIN_GROUP:
                    L[c, t] += n * _lq(r[m], None if act is None else act[m], each) / (n + n2)
    return np.clip(np.exp(L), F_MIN, F_MAX)


def group_factors(F: np.ndarray, gch: np.ndarray, n_groups: int) -> np.ndarray:
    """Each group's factor per time bin: the median over its channels (for channels of another
    skeleton, known only by group)."""
    out = np.ones((n_groups, F.shape[1]))
    for g in range(n_groups):
        m = gch == g
        if m.any():
            out[g] = np.median(F[m], 0)
    return out


def to_json(F: np.ndarray, channels: list[str], gch: np.ndarray, group_names: tuple[str, ...],
            chosen: dict[str, Any]) -> dict[str, Any]:
    gf = group_factors(F, gch, len(group_names))
    return {"channels": {c: [round(float(v), 4) for v in F[i]] for i, c in enumerate(channels)},
            "groups": {n: [round(float(v), 4) for v in gf[g]] for g, n in enumerate(group_names)},
            "chosen": chosen}


def from_json(d: dict[str, Any] | None, channels: list[str], gch: np.ndarray, group_names: tuple[str, ...],
              n_tb: int) -> np.ndarray:
    """F for ``channels`` from a ``to_json`` dict: a channel's own factors, else its group's, else 1."""
    F = np.ones((len(channels), n_tb))
    if not d:
        return F
    own, groups = d.get("channels", {}), d.get("groups", {})
    for i, c in enumerate(channels):
        v = own.get(c)
        if v is None and 0 <= gch[i] < len(group_names):
            v = groups.get(group_names[gch[i]])
        if v is not None:
            if len(v) != n_tb:
                raise ValueError(f"calibration of {c}: {len(v)} time bins, the model has {n_tb}")
            F[i] = v
    return F


def check(F: Any, n_ch: int, n_tb: int, where: str) -> np.ndarray:
    F = np.asarray(F, float)
    if F.shape != (n_ch, n_tb) or not np.all(np.isfinite(F)) or np.any(F <= 0):
        raise ValueError(f"{where}: calibration must be ({n_ch}, {n_tb}) finite factors > 0 (got {F.shape})")
    return np.ascontiguousarray(F)


def scores(z: np.ndarray, std: np.ndarray, err: np.ndarray) -> dict[str, float]:
    """Share within 1 and 2 std and the Gaussian negative log-likelihood per value."""
    s = np.maximum(std, 1e-6)
    return {"within_1std": float(np.mean(z <= 1)), "within_2std": float(np.mean(z <= 2)),
            "nll": float(np.mean(0.5 * (err / s) ** 2 + np.log(s) + 0.5 * math.log(2 * math.pi))), "n": int(len(z))}
