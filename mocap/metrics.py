"""Scoring a fill against the truth, the same way for every protocol.

``values(case, filled, std)`` turns one scored case into a ``Values`` table: one entry per
erased value of a scored (angle) channel, with its error, reported std, gap length, time since
its gap began and joint group, plus the onset and root-translation figures.  ``summarise`` pools
any number of tables (takes, seeds, activities) and returns ``(metric, value, n)`` triples, so an
aggregate is computed over the pooled values (an RMS over all erased values, a median over all
gap onsets), never as a mean of per-take figures.

Definitions
-----------
gap            a maximal run of erased frames of one channel.  Its *length* is the run's
               duration in seconds; a value's *time since onset* is ``k / fps`` where ``k`` is
               the frame's index in its run (0 for the first erased frame).
rms_deg[len A-Bs]    RMS of the wrapped angle error (degrees) over values in gaps of length
               in [A, B) seconds (LENGTH_BINS).
rms_deg[since first] the first erased frame of every gap (k = 0).
rms_deg[since A-Bs]  values with A <= k/fps < B, excluding the first frame (SINCE_BINS): the
               bins are disjoint.
rms_deg[group G]     by joint group (``protocols.GAP_GROUPS`` plus ``other``).
onset_err_median_deg median |error| of the first erased frame, over gaps that start after an
               observed frame; onset_truth_step_median_deg is, over the same gaps, the median
               |truth[t0] - truth[t0-1]| (the performer's own step from the last observed frame);
               onset_err_over_step their ratio.
rms_deg[first 0.1s] / hold_rms_deg[first 0.1s]  RMS over values with k/fps < 0.1 s of the fill
               and of holding truth[t0-1], over the same values (gaps that start after an
               observed frame).
within_1std / within_2std  share of erased values with |error| <= k * max(std, STD_FLOOR).
nll_per_value  mean Gaussian negative log-likelihood of the truth under N(fill, max(std,
               STD_FLOOR)^2), nats per value, std in degrees.  STD_FLOOR = 0.1 degree.
               When the method reports std 0 for every erased value (nn, for instance) the
               three calibration figures are None ("n/a"): no number is made up.
root_pos_rms_cm / root_pos_max_cm / hold_root_pos_rms_cm  over frames where any of root.tx,
               root.ty, root.tz is erased (and an earlier frame observed it, so hold is defined):
               the 3-D distance between filled and true root position, in cm.  The length unit
               comes from the ASF ``:units length L`` (mocap.asf keeps it in
               ``Skeleton.units``): CMU's convention is that lengths are inches divided by L
               (1 unit = 1/0.45 inch = 5.644 cm for L = 0.45; CMU's FAQ: multiply by
               (1/0.45) * 2.54 / 100 for metres).  Without an ASF (BVH, CSV) the figures are in the
               file's own units and named ``root_pos_rms_units`` etc.
unknown truth  an erased value whose truth is NaN (a recording's own dropout, replayed with more
               values dropped) is in its gap's structure but scored nowhere: not in any figure, nor
               as a gap's onset or a root frame.
step_err_rms_deg / pop_p99_deg / pop_max_deg / pop_over_2deg  steps inside gaps: over erased
               values after a gap's first frame (k >= 1), the fill's own step d_f = wrap(fill[t] -
               fill[t-1]) against the truth's d_t = wrap(truth[t] - truth[t-1]); step_err is RMS of
               wrap(d_f - d_t), a *pop* is max(|d_f| - |d_t|, 0) (how much further the fill jumped in
               one frame than the performer moved: 0 for a fill that moves no more than the truth);
               its 99th percentile, maximum and the share above 2 degrees.  truth_step_rms_deg is
               RMS of d_t over the same values, for scale.  (The first frame's jump is the onset
               figures'.)
joint_pos_mean_cm / joint_pos_p95_cm  marker-like error: forward kinematics (mocap.fk) of truth
               and fill, the 3-D distance of every joint on every frame where its position depends
               on an erased value (a filled angle of it or up its chain, or the root translation),
               in cm; mean and 95th percentile.  Needs the case's skeleton (``info["fk"]``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mocap.representation import is_angle, wrap180

LENGTH_BINS = ((0.0, 0.1), (0.1, 0.25), (0.25, 0.5), (0.5, 1.0), (1.0, 2.0), (2.0, np.inf))
SINCE_BINS = ((0.0, 0.05), (0.05, 0.1), (0.1, 0.25), (0.25, 0.5), (0.5, 1.0), (1.0, 2.0), (2.0, np.inf))
ONSET_WINDOW_S = 0.1
STD_FLOOR = 0.1  # degrees (and file length units); below it a reported std is taken as 0.1
ROOT_TRANSLATION = ("root.tx", "root.ty", "root.tz")


def bin_label(lo: float, hi: float) -> str:
    if np.isinf(hi):
        return f">={lo:g}s"
    if lo == 0.0 and hi <= 0.1:
        return f"<{hi:g}s" if hi == 0.1 else f"0-{hi:g}s"
    return f"{lo:g}-{hi:g}s"


def cm_per_unit(skeleton: Any) -> float | None:
    """Centimetres per file length unit from an ASF skeleton's ``:units length``; None without one."""
    units = getattr(skeleton, "units", None)
    if not units or "length" not in units:
        return None
    return 2.54 / float(units["length"])


def gap_structure(missing: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For a (T, C) erased mask: ``since`` (frames since the run began, -1 where observed),
    ``length`` (frames in the run, 0 where observed) and ``start`` (the run's first frame, -1)."""
    missing = np.asarray(missing, bool)
    T, C = missing.shape
    since = np.full((T, C), -1, int)
    length = np.zeros((T, C), int)
    start = np.full((T, C), -1, int)
    t = np.arange(T)
    for c in range(C):
        m = missing[:, c]
        if not m.any():
            continue
        d = np.diff(np.concatenate([[0], m.astype(np.int8), [0]]))
        a, b = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
        rid = np.cumsum(d[:-1] == 1) - 1  # run index of each frame (valid where m)
        st = a[rid[m]]
        start[m, c] = st
        since[m, c] = t[m] - st
        length[m, c] = (b - a)[rid[m]]
    return since, length, start


def gaussian_nll(err: np.ndarray, std: np.ndarray, floor: float = STD_FLOOR) -> np.ndarray:
    """-log N(err; 0, s^2) with s = max(std, floor): 0.5 log(2 pi s^2) + err^2 / (2 s^2)."""
    s = np.maximum(np.asarray(std, dtype=np.float64), floor)
    return 0.5 * np.log(2.0 * np.pi * s**2) + 0.5 * (np.asarray(err, dtype=np.float64) / s) ** 2


@dataclass
class Values:
    """The erased, scored values of one or more cases (1-D arrays of equal length unless noted)."""

    err: np.ndarray          # wrapped angle error, degrees
    std: np.ndarray          # reported std, degrees
    since: np.ndarray        # seconds since the gap began
    first: np.ndarray        # bool: first erased frame of its gap
    length: np.ndarray       # seconds, the gap's length
    group: np.ndarray        # joint group name
    hold_err: np.ndarray     # error of holding truth[t0-1] (nan where the gap starts at frame 0)
    onset_err: np.ndarray    # per gap (own length): |error| at its first frame, gaps with t0 > 0
    onset_step: np.ndarray   # per gap: |truth[t0] - truth[t0-1]|
    root_err: np.ndarray     # per frame with the root translation erased: 3-D error (root_unit)
    root_hold_err: np.ndarray
    root_unit: str = "cm"
    extra: dict[str, Any] = field(default_factory=dict)
    # per (frame, joint) moved by an erased value: 3-D joint-position error, cm (mocap.fkerror)
    joint_err: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # per erased value (NaN at a gap's first frame): fill step minus truth step, and the pop
    step_err: np.ndarray = field(default_factory=lambda: np.zeros(0))
    truth_step: np.ndarray = field(default_factory=lambda: np.zeros(0))
    pop: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @staticmethod
    def concat(tables: list[Values]) -> Values:
        if not tables:
            raise ValueError("no values to pool")
        units = {t.root_unit for t in tables if t.root_err.size}
        if len(units) > 1:
            raise ValueError(f"cannot pool root errors in different units ({sorted(units)})")
        kw = {f: np.concatenate([getattr(t, f) for t in tables]) for f in
              ("err", "std", "since", "first", "length", "group", "hold_err", "onset_err", "onset_step",
               "root_err", "root_hold_err", "joint_err", "step_err", "truth_step", "pop")}
        return Values(**kw, root_unit=units.pop() if units else tables[0].root_unit)


def values(case: Any, filled: np.ndarray, std: np.ndarray | None, groups: dict[str, tuple[str, ...]]) -> Values:
    """The scored erased values of one case (``protocols.Case``): see the module docstring.

    filled, std : (T, C) in the case's units; std None means none reported (zeros).
    groups : joint group -> bone names; channels of no group are ``other`` (``root`` is a group
        when the protocol lists it).
    """
    truth = np.asarray(case.truth, dtype=np.float64)
    filled = np.asarray(filled, dtype=np.float64)
    T, C = truth.shape
    std = np.zeros((T, C)) if std is None else np.broadcast_to(np.asarray(std, dtype=np.float64), (T, C))
    std = np.where(np.isfinite(std), std, 0.0)
    missing = ~np.asarray(case.observed, bool)
    ang = np.array([is_angle(c) for c in case.channels])
    scored = np.asarray(case.scored, bool) & ang
    since, length, start = gap_structure(missing)
    fps = float(case.fps)

    err = wrap180(filled - truth)
    prev = np.vstack([truth[:1], truth[:-1]])  # truth[t-1]
    held = np.where(start > 0, truth[np.clip(start - 1, 0, None), np.arange(C)[None, :]], np.nan)
    with np.errstate(invalid="ignore"):  # nan where a gap starts at frame 0: no last value to hold
        hold_err = wrap180(held - truth)

    sel = missing & scored[None, :] & np.isfinite(truth)   # (a truth the take never had: not scored)
    fprev = np.vstack([filled[:1], filled[:-1]])
    df, dt = wrap180(filled - fprev), wrap180(truth - prev)
    inner = since >= 1   # after the gap's first frame: fill[t-1] is a fill too
    step_err = np.where(inner, wrap180(df - dt), np.nan)
    pop = np.where(inner, np.maximum(np.abs(df) - np.abs(dt), 0.0), np.nan)
    tstep = np.where(inner, np.abs(dt), np.nan)
    bone_group = {}
    for g, bones in groups.items():
        for b in bones:
            bone_group[b] = g
    gname = np.array([bone_group.get(c.split(".", 1)[0], "other") for c in case.channels], dtype=object)

    onset = sel & (since == 0) & (start > 0)
    # root position error over frames where the root translation is erased (and was seen before)
    pos = {c: i for i, c in enumerate(case.channels)}
    rt = [pos[c] for c in case.info.get("root_translation", ROOT_TRANSLATION) if c in pos]
    scale = case.info.get("cm_per_unit")
    unit = "cm" if scale else "units"
    if rt:
        rmiss = missing[:, rt].any(1)
        seen_before = np.cumsum(~missing[:, rt].any(1)) > 0
        seen_before = np.concatenate([[False], seen_before[:-1]])
        rows = rmiss & seen_before & np.isfinite(truth[:, rt]).all(1)
        d = (filled[:, rt] - truth[:, rt])[rows]
        # hold keeps each erased component at its value on the frame before its gap
        hstart = np.where(missing[:, rt], start[:, rt], -1)[rows]
        tr = truth[:, rt][rows]
        hv = np.where(hstart > 0, truth[np.clip(hstart - 1, 0, None), np.array(rt)[None, :]], tr)
        k = scale or 1.0
        root_err = np.sqrt((d**2).sum(1)) * k
        root_hold = np.sqrt(((hv - tr) ** 2).sum(1)) * k
    else:
        root_err = root_hold = np.zeros(0)
    return Values(
        err=err[sel], std=std[sel], since=since[sel] / fps, first=(since == 0)[sel], length=length[sel] / fps,
        group=np.broadcast_to(gname[None, :], (T, C))[sel], hold_err=hold_err[sel],
        onset_err=np.abs(err[onset]), onset_step=np.abs(wrap180(truth - prev)[onset]),
        root_err=root_err, root_hold_err=root_hold, root_unit=unit,
        joint_err=_joint_err(case, filled, missing),
        step_err=step_err[sel], truth_step=tstep[sel], pop=pop[sel],
    )


def _joint_err(case: Any, filled: np.ndarray, missing: np.ndarray) -> np.ndarray:
    kin = case.info.get("fk")  # the case's mocap.fk.Kinematics, when its skeleton is known
    if kin is None:
        return np.zeros(0)
    from mocap.fkerror import joint_errors_cm

    return joint_errors_cm(kin, case.truth, filled, missing)


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def _binned(v: Values, keep: np.ndarray, tag: str) -> list[tuple[str, float | None, int]]:
    """RMS by gap length and by time since onset over the values ``keep`` selects."""
    out: list[tuple[str, float | None, int]] = []
    for lo, hi in LENGTH_BINS:
        m = keep & (v.length >= lo) & (v.length < hi)
        if m.any():
            out.append((f"rms_deg[{tag}len {bin_label(lo, hi)}]", _rms(v.err[m]), int(m.sum())))
    m = keep & v.first
    if m.any():
        out.append((f"rms_deg[{tag}since first]", _rms(v.err[m]), int(m.sum())))
    for lo, hi in SINCE_BINS:
        m = keep & (v.since >= lo) & (v.since < hi) & ~v.first
        if m.any():
            out.append((f"rms_deg[{tag}since {bin_label(lo, hi)}]", _rms(v.err[m]), int(m.sum())))
    return out


def summarise(v: Values, by_group_bins: bool = True) -> list[tuple[str, float | None, int]]:
    """(metric, value, n) for pooled values; bins with no values are left out.  With
    ``by_group_bins`` the length and onset bins are also given per joint group
    (``rms_deg[group G, len A-Bs]``, ``rms_deg[group G, since ...]``)."""
    out: list[tuple[str, float | None, int]] = []
    n = v.err.size
    if n:
        out.append(("rms_deg", _rms(v.err), n))
    out += _binned(v, np.ones(n, bool), "")
    for g in sorted(set(v.group.tolist())):
        m = v.group == g
        out.append((f"rms_deg[group {g}]", _rms(v.err[m]), int(m.sum())))
        if by_group_bins:
            out += _binned(v, m, f"group {g}, ")
    if v.onset_err.size:
        e, s = float(np.median(v.onset_err)), float(np.median(v.onset_step))
        k = int(v.onset_err.size)
        out += [("onset_err_median_deg", e, k), ("onset_truth_step_median_deg", s, k),
                ("onset_err_over_step", e / s if s > 0 else None, k)]
    w = (v.since < ONSET_WINDOW_S) & np.isfinite(v.hold_err)
    if w.any():
        out += [(f"rms_deg[first {ONSET_WINDOW_S:g}s]", _rms(v.err[w]), int(w.sum())),
                (f"hold_rms_deg[first {ONSET_WINDOW_S:g}s]", _rms(v.hold_err[w]), int(w.sum()))]
    if n:
        if np.any(v.std > 0):
            s = np.maximum(v.std, STD_FLOOR)
            a = np.abs(v.err)
            out += [("within_1std", float(np.mean(a <= s)), n), ("within_2std", float(np.mean(a <= 2 * s)), n),
                    ("nll_per_value", float(np.mean(gaussian_nll(v.err, v.std))), n)]
        else:
            out += [("within_1std", None, n), ("within_2std", None, n), ("nll_per_value", None, n)]
    if v.root_err.size:
        u, k = v.root_unit, int(v.root_err.size)
        out += [(f"root_pos_rms_{u}", _rms(v.root_err), k), (f"root_pos_max_{u}", float(v.root_err.max()), k),
                (f"hold_root_pos_rms_{u}", _rms(v.root_hold_err), k)]
    inner = np.isfinite(v.pop) if v.pop.size == n else np.zeros(0, bool)
    if inner.any():
        k, p = int(inner.sum()), v.pop[inner]
        out += [("step_err_rms_deg", _rms(v.step_err[inner]), k), ("truth_step_rms_deg", _rms(v.truth_step[inner]), k),
                ("pop_p99_deg", float(np.percentile(p, 99)), k), ("pop_max_deg", float(p.max()), k),
                ("pop_over_2deg", float(np.mean(p > 2.0)), k)]
    if v.joint_err.size:
        k = int(v.joint_err.size)
        out += [("joint_pos_mean_cm", float(v.joint_err.mean()), k),
                ("joint_pos_p95_cm", float(np.percentile(v.joint_err, 95)), k)]
    return out
