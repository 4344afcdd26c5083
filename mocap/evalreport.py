"""The printed table and the figure of an ``mocap.evaluate.evaluate`` result.

The table has one block per erasure pattern: metrics down, then the aggregates (walk, turn,
run, nonloco, all) and the takes across (the per-group bins are in the JSON only); ``n/a`` where a figure does not apply (calibration of a
method that reports no std).  The figure shows, for a few cases, the erased channels that move
most: truth, the fill and its 2-std band around the channel's longest gap.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from mocap.metrics import gap_structure

MAX_TAKE_COLUMNS = 14


def _fmt(v: Any) -> str:
    if v is None:
        return "n/a"
    return f"{v:.3f}" if abs(v) < 100 else f"{v:.1f}"


def format_table(result: dict[str, Any]) -> str:
    rows = result["results"]
    head = f"protocol {result['protocol']}  method {result['method']}" + ("" if result["causal"] else "  (offline: not causal)")
    head += f"  split {result.get('split')}"
    if result.get("split") == "test":
        head += " (TEST figures: report, never tune on them)"
    if result.get("seeds"):
        head += f"  seeds {','.join(map(str, result['seeds']))}"
    if result.get("train_seconds") is not None:
        head += f"  trained in {result['train_seconds']:.1f} s"
    lines = [head]
    seen = sorted({r["test"] for r in rows if r.get("in_training")})
    if seen:
        lines.append(f"NOTE: the model was trained on {', '.join(seen)}: those figures are not held out")
    for erased in dict.fromkeys(r["erased"] for r in rows):
        block = [r for r in rows if r["erased"] == erased]
        cols: list[tuple[str, str]] = []
        for r in block:
            key = (r["test"], r["activity"]) if r["test"] == "all" else (r["test"], "")
            if key not in cols:
                cols.append(key)
        aggs = [c for c in cols if c[0] == "all"]
        takes = [c for c in cols if c[0] != "all"]
        if len(takes) == 1:
            aggs = []  # one take: its own column says it all
        shown = aggs + takes[:MAX_TAKE_COLUMNS]
        cell: dict[tuple[str, str, str], Any] = {}
        metrics: list[str] = []
        # the pooled "all" rows have every bin any take has, in mocap.metrics' order
        for r in sorted(block, key=lambda r: (r["test"], r["activity"]) != ("all", "all")):
            key = (r["test"], r["activity"]) if r["test"] == "all" else (r["test"], "")
            cell[(key[0], key[1], r["metric"])] = r["value"]
            if r["metric"] not in metrics:
                metrics.append(r["metric"])
        metrics = [m for m in metrics if not m.startswith("rms_deg[group ") or "," not in m]  # group x bin: --json
        pooled = {r["metric"] for r in block if r["test"] == "all"}
        metrics = [m for m in metrics if m not in pooled] + [m for m in metrics if m in pooled]  # protocol's own first
        names = [a if t == "all" else t for t, a in shown]
        w0 = max(len(m) for m in metrics + ["metric"])
        w = [max(8, len(n)) for n in names]
        lines.append("")
        lines.append(f"erased: {erased}" + (f"  (first {MAX_TAKE_COLUMNS} of {len(takes)} takes shown; all in --json)"
                                             if len(takes) > MAX_TAKE_COLUMNS else ""))
        lines.append(f"{'metric':<{w0}}  " + "  ".join(f"{n:>{k}}" for n, k in zip(names, w)))
        for m in metrics:
            vals = []
            for (t, a), k in zip(shown, w):
                v = cell.get((t, a, m), "")
                vals.append(f"{'' if v == '' else _fmt(v):>{k}}")
            lines.append(f"{m:<{w0}}  " + "  ".join(vals))
    return "\n".join(lines)


def plot(result: dict[str, Any], path: str, max_cases: int = 4, max_channels: int = 3) -> None:
    """Truth, fill and the fill's 2-std band for the erased channels that move most, around each
    channel's longest gap (1 s either side), for up to ``max_cases`` cases (one per activity first)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mocap.splits import ACTIVITY

    cases, fills, stds = result["_cases"], result["_fills"], result["_stds"]
    if not cases:
        raise ValueError("no cases to plot (evaluate(..., keep=False) drops them)")
    first_of: dict[str, int] = {}
    for i, c in enumerate(cases):
        first_of.setdefault(ACTIVITY.get(c.test, "unknown"), i)
    order = list(first_of.values()) + [i for i in range(len(cases)) if i not in first_of.values()]
    order = order[:max_cases]
    fig, axes = plt.subplots(len(order), max_channels, figsize=(4.2 * max_channels, 2.6 * len(order)), squeeze=False)
    for row, i in enumerate(order):
        case, fill, std = cases[i], fills[i], stds[i]
        miss = case.missing & case.scored[None, :]
        cols = np.flatnonzero(miss.any(0))
        cols = cols[np.argsort(-case.truth[:, cols].std(0))][:max_channels]
        _, length, start = gap_structure(miss)
        fps = case.fps
        for j in range(max_channels):
            ax = axes[row, j]
            if j >= len(cols):
                ax.axis("off")
                continue
            c = cols[j]
            k = int(np.argmax(length[:, c]))
            a, b = int(start[k, c]), int(start[k, c] + length[k, c])
            lo, hi = max(0, a - int(fps)), min(case.truth.shape[0], b + int(fps))
            t = np.arange(lo, hi) / fps
            m = miss[lo:hi, c]
            f = np.where(m, fill[lo:hi, c], np.nan)
            s = np.where(m, std[lo:hi, c], np.nan)
            ax.plot(t, case.truth[lo:hi, c], "k-", lw=1.3, label="truth")
            ax.plot(t, f, "r-", lw=1.2, label=result["method"])
            ax.fill_between(t, f - 2 * s, f + 2 * s, color="r", alpha=0.2, lw=0, label="2 std")
            ax.fill_between(t, 0, 1, where=m, color="0.9", transform=ax.get_xaxis_transform(), zorder=0)
            ax.set_title(f"{case.test} {case.erased}: {case.channels[c]}", fontsize=8)
            ax.set_xlabel("s", fontsize=7)
            ax.tick_params(labelsize=7)
            if row == 0 and j == 0:
                ax.legend(fontsize=7)
    split = result.get("split")
    fig.suptitle(f"{result['protocol']} ({split}): {result['method']}, truth, fill and 2-std band (grey = erased)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
