"""The demo's figures, computed by ``mocap.metrics`` (the same scoring as ``lacuna eval``), and its
printed table.

``score(case, filled, std)`` gives, for one method's fill of the replayed take: RMS over every
dropped value, by gap length (short 0.1-0.25 s, long 0.5-2 s, and every length bin of
``metrics.LENGTH_BINS``), the onset figures (median error of the first erased frame beside the
truth's own step from the last observed frame; RMS over the first 100 ms beside holding the last
value over the same values) and the calibration (share within 1 and 2 reported std, Gaussian
negative log-likelihood per value; None where the method reports no std), and the pops inside gaps
(share of values after a gap's first frame whose step is over 2 deg beyond the truth's own, and the
largest such pop).
"""
from __future__ import annotations

import dataclasses
import os
from typing import Any

import numpy as np

from mocap import metrics
from mocap.protocols import GAP_GROUPS, Case
from mocap.representation import is_angle

SHORT = (0.1, 0.25)  # seconds: the short dropouts the demo reports apart
LONG = (0.5, 2.0)
FIGURES = ("rms_deg", "rms_short_deg", "rms_long_deg", "onset_err_median_deg", "onset_truth_step_median_deg",
           "onset_err_over_step", "rms_first_100ms_deg", "hold_rms_first_100ms_deg", "within_1std", "within_2std",
           "nll_per_value", "pop_over_2deg", "pop_max_deg")


def make_case(name: str, truth: np.ndarray, observed: np.ndarray, channels: list[str], fps: float,
              cm_per_unit: float | None, pattern: str) -> Case:
    """The replayed take as a ``protocols.Case``: every angle channel scored, as in the gaps protocol."""
    scored = np.array([is_angle(c) for c in channels])
    return Case(name, pattern, np.asarray(truth, np.float64), np.asarray(observed, bool), list(channels), fps, scored,
                {"cm_per_unit": cm_per_unit})


def _pooled(v: metrics.Values, keep: np.ndarray) -> tuple[float | None, int]:
    """``metrics.summarise``'s pooled RMS over the values ``keep`` selects (per-gap figures dropped)."""
    if not keep.any():
        return None, 0
    empty = np.zeros(0)
    sub = dataclasses.replace(v, **{f: getattr(v, f)[keep] for f in
                                    ("err", "std", "since", "first", "length", "group", "hold_err")},
                              onset_err=empty, onset_step=empty, root_err=empty, root_hold_err=empty)
    rows = {k: (x, n) for k, x, n in metrics.summarise(sub, by_group_bins=False)}
    return rows["rms_deg"]


def score(case: Case, filled: np.ndarray, std: np.ndarray | None) -> dict[str, Any]:
    """The demo's figures for one fill (see the module docstring); ``n_*`` count the values pooled."""
    v = metrics.values(case, filled, std, GAP_GROUPS)
    rows = {k: (x, n) for k, x, n in metrics.summarise(v, by_group_bins=False)}
    out: dict[str, Any] = {}
    short, n_short = _pooled(v, (v.length >= SHORT[0]) & (v.length < SHORT[1]))
    long_, n_long = _pooled(v, (v.length >= LONG[0]) & (v.length < LONG[1]))
    w = f"first {metrics.ONSET_WINDOW_S:g}s"
    names = {"rms_deg": "rms_deg", "onset_err_median_deg": "onset_err_median_deg",
             "onset_truth_step_median_deg": "onset_truth_step_median_deg", "onset_err_over_step": "onset_err_over_step",
             f"rms_deg[{w}]": "rms_first_100ms_deg", f"hold_rms_deg[{w}]": "hold_rms_first_100ms_deg",
             "within_1std": "within_1std", "within_2std": "within_2std", "nll_per_value": "nll_per_value",
             "pop_over_2deg": "pop_over_2deg", "pop_max_deg": "pop_max_deg"}
    for src, dst in names.items():
        x, n = rows.get(src, (None, 0))
        out[dst] = x
        out[f"n_{dst}"] = n
    out.update(rms_short_deg=short, n_rms_short_deg=n_short, rms_long_deg=long_, n_rms_long_deg=n_long)
    out["by_length"] = {k[len("rms_deg[len "):-1]: {"rms_deg": x, "n": n} for k, (x, n) in rows.items()
                        if k.startswith("rms_deg[len ")}
    out["by_since"] = {k[len("rms_deg[since "):-1]: {"rms_deg": x, "n": n} for k, (x, n) in rows.items()
                       if k.startswith("rms_deg[since ")}
    out["by_group"] = {k[len("rms_deg[group "):-1]: {"rms_deg": x, "n": n} for k, (x, n) in rows.items()
                       if k.startswith("rms_deg[group ")}
    return out


def gap_lengths(bursts: list[tuple[str, int, int]], fps: float) -> dict[str, int]:
    """How many dropout bursts are short, medium, long."""
    d = [(b - a) / fps for _, a, b in bursts]
    return {"short (0.1-0.25 s)": sum(SHORT[0] <= x < SHORT[1] for x in d),
            "medium (0.25-0.5 s)": sum(SHORT[1] <= x < LONG[0] for x in d),
            "long (0.5-2 s)": sum(LONG[0] <= x < LONG[1] for x in d),
            "other": sum(x < SHORT[0] or x >= LONG[1] for x in d)}


def _f(v: float | None, spec: str = "6.2f") -> str:
    return "-" if v is None else format(v, spec)


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{100 * v:.2f}%"


def format_report(rep: dict[str, Any]) -> str:
    """The table the demo prints (every figure is in demo.json too)."""
    L = [f"motion: {rep['motion']}", f"replayed: {rep['take']['about']}", f"dropouts: {rep['dropouts']['about']}", ""]
    L.append("accuracy on the dropped values, degrees (mocap.metrics; n/a = the method reports no std)")
    L.append(f"{'method':<8} {'path':<9} {'all':>6} {'short':>6} {'long':>6} | {'onset':>6} {'step':>6} "
             f"{'0-100ms':>7} {'hold':>6} | {'in 2sd':>6} {'NLL':>6} | {'pops':>6} {'max':>5} | {'p50 ms':>7} {'p99 ms':>7}")
    for name, r in rep["results"].items():
        s = r["scores"]
        lat = r.get("latency") or {}
        path = "daemon" if r["through_daemon"] else "offline"
        p50 = _f(lat.get("p50_ms"), "7.3f") if lat else "-"
        p99 = _f(lat.get("p99_ms"), "7.3f") if lat else "-"
        L.append(f"{name:<8} {path:<9} {_f(s['rms_deg']):>6} {_f(s['rms_short_deg']):>6} {_f(s['rms_long_deg']):>6} | "
                 f"{_f(s['onset_err_median_deg']):>6} {_f(s['onset_truth_step_median_deg']):>6} "
                 f"{_f(s['rms_first_100ms_deg'], '7.2f'):>7} {_f(s['hold_rms_first_100ms_deg']):>6} | "
                 f"{_f(s['within_2std'], '6.3f'):>6} {_f(s['nll_per_value']):>6} | "
                 f"{_pct(s['pop_over_2deg']):>6} {_f(s['pop_max_deg'], '5.1f'):>5} | {p50:>7} {p99:>7}")
    L += ["", "short = gaps of 0.1-0.25 s, long = 0.5-2 s; onset = median |error| of the first dropped frame, "
              "step = the performer's own median step into that frame; 0-100ms = RMS over each gap's first 100 ms, "
              "hold = holding the last value over the same values; in 2sd = share within 2 reported std (0.95 is "
              "calibrated); NLL = Gaussian negative log-likelihood per value (nats, std floor "
              f"{metrics.STD_FLOOR:g} deg); pops = share of values inside gaps whose step is over 2 deg beyond "
              "the performer's own, max = the largest; ms = round trip through the daemon"]
    for n in rep["notes"]:
        L.append(f"note: {n}")
    L += ["", f"fills vs truth (2-std band): {rep['plots']['fills']}", f"latency histogram: {rep['plots']['latency']}",
          f"json: {os.path.join(os.path.dirname(rep['plots']['fills']), 'demo.json')}",
          f"total {rep['total_seconds']:.0f} s"]
    return "\n".join(L)
