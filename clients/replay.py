"""``lacuna replay FILE``: stream a recorded take to the daemon and score what comes back.

Frames go out at the take's frame rate times ``speed`` (absolute perf_counter deadlines; 0 = as
fast as the daemon answers), one request/reply each, with the values a drop pattern erased sent
as missing.  The filled take is written in the input's format: captured values are copied from
the input itself (the daemon echoes them only to float32), the daemon's values are used where
it filled.  The report gives RMS error on the erased values (wrapped for angles) and the round
trips of every frame.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from clients.client import Client
from clients.loadgen import percentiles
from daemon import wire
from mocap.motion import Motion
from mocap.representation import is_angle
from mocap.rootrot import wrap180

PROGRESS_EVERY_S = 0.5


@dataclass
class ReplayResult:
    """Outcome of one replay.

    filled : (T, C) the written take.  std : (T, C) the daemon's standard deviations.
    sent_observed : (T, C) bool, what was sent as captured.  daemon_filled : (T, C) bool.
    rtt_ms : (n_answered,) round trips.  status : {status: count}.
    """

    motion: Motion
    filled: np.ndarray
    std: np.ndarray
    sent_observed: np.ndarray
    daemon_filled: np.ndarray
    rtt_ms: np.ndarray
    proc_us: np.ndarray
    status: dict[str, int] = field(default_factory=dict)
    frame_status: list[str] = field(default_factory=list)
    dropped: int = 0
    held: int = 0
    echo_max_err: float = 0.0
    model: str = ""
    wall_s: float = 0.0


def replay(endpoint: str, motion: Motion, observed: np.ndarray, *, speed: float = 1.0, stream: str = "replay",
           model: str | None = None, progress: bool = True, timeout_s: float = 2.0) -> ReplayResult:
    """Stream ``motion`` (T, C) with ``observed`` (T, C) to the daemon; see the module docstring."""
    T, C = motion.frames.shape
    if observed.shape != (T, C):
        raise ValueError(f"observed mask has shape {observed.shape}, the take is {(T, C)}")
    if speed < 0:
        raise ValueError(f"--speed must be >= 0 (got {speed})")
    out = np.full((T, C), np.nan)
    std = np.zeros((T, C))
    dfill = np.zeros((T, C), bool)
    rtt = np.full(T, np.nan)
    proc = np.full(T, np.nan)
    status: dict[str, int] = {}
    frame_status = ["dropped"] * T
    dropped = 0
    echo = 0.0
    model_name = ""
    period = 0.0 if speed == 0 else 1.0 / (motion.fps * speed)
    with Client(endpoint, stream, channels=list(motion.channels), model=model, timeout_s=timeout_s) as c:
        ack = c.hello()
        model_name = ack.model
        t0 = time.perf_counter()
        last_report = t0
        for k in range(T):
            if period:
                due = t0 + k * period
                while (left := due - time.perf_counter()) > 0:
                    time.sleep(left - 0.0005 if left > 0.001 else 0)  # sleep most, spin the last half millisecond
            ts = time.perf_counter()
            msg = c.fill(motion.frames[k], observed[k], t=k / motion.fps)
            rtt[k] = (time.perf_counter() - ts) * 1000.0
            if isinstance(msg, wire.Drop):
                dropped += 1
                continue
            a = np.asarray(msg.angles, dtype=np.float64)
            out[k] = a
            std[k] = msg.std
            dfill[k] = msg.filled
            proc[k] = msg.proc_us
            status[msg.status] = status.get(msg.status, 0) + 1
            frame_status[k] = msg.status
            o = observed[k]
            if o.any():
                echo = max(echo, float(np.max(np.abs(a[o] - motion.frames[k, o].astype(np.float32)))))
            if progress and time.perf_counter() - last_report > PROGRESS_EVERY_S:
                last_report = time.perf_counter()
                print(f"\r  replay {stream}: {k + 1}/{T} frames ({100 * (k + 1) / T:.0f}%)", end="", file=sys.stderr,
                      flush=True)
        wall = time.perf_counter() - t0
    if progress:
        print(f"\r  replay {stream}: {T}/{T} frames (100%), {wall:.1f} s      ", file=sys.stderr, flush=True)
    # captured values are the input's own (exact); the daemon's are used where it filled
    written = np.where(observed, motion.frames, out)
    # values left missing (dropped frames, pass-through channels): hold the last known value so a
    # file format without NaN can be written; counted and reported
    miss = ~np.isfinite(written)
    held = int(miss.sum())
    if held:
        written = _hold_forward(written)
    ok = np.isfinite(rtt)
    return ReplayResult(motion, written, std, observed.copy(), dfill, rtt[ok], proc[np.isfinite(proc)], status,
                        frame_status, dropped, held, echo, model_name, wall)


def fill_messages(res: ReplayResult, stream: str = "replay") -> list[wire.FillMsg]:
    """The written take as one wire ``fill`` per frame (for writing a recording)."""
    m = res.motion
    return [wire.FillMsg(stream, k, k / m.fps, res.filled[k].astype(np.float32), res.daemon_filled[k],
                         res.std[k].astype(np.float32), s if s in wire.STATUSES else "passthrough", res.model, 0)
            for k, s in enumerate(res.frame_status)]


def _hold_forward(x: np.ndarray) -> np.ndarray:
    out = x.copy()
    for j in range(out.shape[1]):
        col = out[:, j]
        good = np.isfinite(col)
        if not good.any():
            col[:] = 0.0
            continue
        idx = np.where(good, np.arange(col.size), 0)
        np.maximum.accumulate(idx, out=idx)
        first = np.argmax(good)
        col[:] = col[idx]
        col[:first] = col[first]
    return out


def errors(truth: np.ndarray, filled: np.ndarray, erased: np.ndarray, channels: list[str]) -> dict[str, Any]:
    """RMS error on the erased values (wrapped degrees for angles; translations apart).

    truth, filled : (T, C);  erased : (T, C) bool, values that were sent as missing and whose
    truth is known.
    """
    # only erased values with a known truth are scored; zero the rest so NaN never enters wrap180
    err = np.where(erased, np.nan_to_num(filled) - np.nan_to_num(truth), 0.0)
    ang = np.array([is_angle(c) for c in channels])
    err[:, ang] = wrap180(err[:, ang])
    ea = erased & ang[None]
    per = {}
    for j in np.flatnonzero(ea.any(0)):
        per[channels[j]] = float(np.sqrt(np.mean(err[ea[:, j], j] ** 2)))
    # the trivial fill on the same values: the last value sent before each erased one (scored
    # where there was one)
    held = _hold_forward(np.where(erased, np.nan, truth)) if ea.any() else truth
    he = ea & np.logical_or.accumulate(~erased, axis=0)
    hold = wrap180(np.nan_to_num(held) - np.nan_to_num(truth))
    return {
        "rms_deg": float(np.sqrt(np.mean(err[ea] ** 2))) if ea.any() else None,
        "hold_rms_deg": float(np.sqrt(np.mean(hold[he] ** 2))) if he.any() else None,
        "erased_values": int(erased.sum()),
        "erased_angle_values": int(ea.sum()),
        "per_channel_rms_deg": per,
    }


def summary(res: ReplayResult, truth_known: np.ndarray | None = None) -> dict[str, Any]:
    """JSON-ready report; ``truth_known`` (T, C) bool marks values the input really has."""
    m = res.motion
    known = np.isfinite(m.frames) if truth_known is None else truth_known & np.isfinite(m.frames)
    erased = ~res.sent_observed & known
    return {
        "source": m.source, "frames": int(m.n_frames), "channels": len(m.channels), "fps": m.fps,
        "model": res.model, "status": res.status, "dropped": res.dropped, "held_values": res.held,
        "echo_max_err": res.echo_max_err, "wall_s": res.wall_s,
        "latency": percentiles(res.rtt_ms),
        "daemon_proc_ms_p50": float(np.median(res.proc_us) / 1000.0) if res.proc_us.size else None,
        "accuracy": errors(m.frames, res.filled, erased, m.channels),
    }


def figures(res: ReplayResult, known: np.ndarray, pattern: str = "", cm_per_unit: float | None = None) -> dict[str, Any] | None:
    """The figures ``lacuna demo`` and ``lacuna eval`` give (``clients.demo_score.score``: RMS by gap
    length and time since onset, the first dropped frame beside the performer's own step, the first
    100 ms beside holding, the share within 1 and 2 reported std, the Gaussian NLL, the pops inside
    gaps), over the values the replay dropped whose truth the take has; None when it dropped none."""
    from clients import demo_score

    m = res.motion
    ang = np.array([is_angle(c) for c in m.channels])
    known = np.asarray(known, bool) & np.isfinite(m.frames)
    if not (known & ~res.sent_observed & ang[None, :]).any():
        return None
    truth = np.where(known, m.frames, np.nan)
    case = demo_score.make_case(str(m.source or "replay"), truth, res.sent_observed, list(m.channels), m.fps,
                                cm_per_unit, pattern)
    with np.errstate(invalid="ignore"):   # (the unknown truths are NaN: mocap.metrics leaves them unscored)
        return demo_score.score(case, res.filled, res.std)


def plot_replay(path: str, res: ReplayResult, known: np.ndarray, title: str = "", n_channels: int = 4) -> str:
    """Truth, the daemon's fill with its 2-std band and holding the last value, on up to
    ``n_channels`` dropped angle channels (one per joint group where the skeleton's groups are
    CMU's, else the most-dropped)."""
    from mocap.protocols import GAP_GROUPS

    m = res.motion
    erased = np.asarray(known, bool) & ~res.sent_observed
    cols = band_channels(m.frames, erased, list(m.channels), GAP_GROUPS, n_channels)
    if not cols:   # (a skeleton whose bones are not CMU's: the channels dropped most, weighed by how they move)
        ang = np.array([is_angle(c) for c in m.channels])
        score = np.where(ang, erased.sum(0) * (np.nan_to_num(m.frames).std(0) + 1e-9), 0)
        cols = [int(j) for j in np.argsort(-score)[:n_channels] if score[j] > 0] or [int(np.argmax(ang))]
    hold = _hold_forward(np.where(res.sent_observed, m.frames, np.nan))   # the fill a studio has without Lacuna
    return plot_fill_band(path, m.frames, res.filled, res.std, erased, list(m.channels), m.fps, cols,
                          others={"hold": hold}, name=res.model or "fill", title=title)


LINE_COLOURS = {"hold": "tab:blue", "interp": "tab:green", "hlm": "tab:purple", "crbm": "tab:brown", "nn": "tab:olive"}


def _spans(e: np.ndarray) -> list[tuple[int, int]]:
    edges = np.flatnonzero(np.diff(np.r_[0, e.astype(int), 0]))
    return list(zip(edges[::2], edges[1::2]))


def band_channels(truth: np.ndarray, erased: np.ndarray, channels: list[str], groups: dict[str, tuple[str, ...]],
                  n: int = 4) -> list[int]:
    """Up to ``n`` angle channels to plot, one per joint group: in each group the channel that moves
    most, groups ranked by how many values they lost and how varied their gaps are."""
    ang = np.array([is_angle(c) for c in channels])
    bone = np.array([c.split(".", 1)[0] for c in channels])
    picks = []
    for bones in groups.values():
        cols = np.flatnonzero(ang & np.isin(bone, bones) & erased.any(0))
        if not cols.size:
            continue
        j = int(cols[np.argmax(truth[:, cols].std(0))])
        if truth[:, j].std() < 1e-6:
            continue
        lens = {b - a for a, b in _spans(erased[:, j])}
        picks.append((len(lens), int(erased[:, j].sum()), j))
    return [j for *_, j in sorted(picks, reverse=True)[:n]]


def plot_fill_band(path: str, truth: np.ndarray, fill: np.ndarray, std: np.ndarray, erased: np.ndarray,
                   channels: list[str], fps: float, cols: list[int], others: dict[str, np.ndarray] | None = None,
                   name: str = "fill", title: str = "") -> str:
    """Truth, one method's fill with its 2-std band (shaded) and other methods' fills as lines, on
    the channels ``cols``; dropped spans greyed and labelled with their length in seconds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    others = others or {}
    t = np.arange(truth.shape[0]) / fps
    fig, axes = plt.subplots(len(cols), 1, figsize=(10, 2.4 * len(cols)), sharex=True, squeeze=False)
    for ax, j in zip(axes[:, 0], cols):
        e = erased[:, j]
        ax.plot(t, truth[:, j], color="k", lw=1.5, label="truth")
        for a, b in _spans(e):
            ax.axvspan(t[a], t[min(b, len(t) - 1)], color="0.92", lw=0)
            ax.annotate(f"{(b - a) / fps:.2f} s", (t[a], 1.0), xycoords=("data", "axes fraction"), fontsize=6,
                        va="bottom", color="0.35")
        for k, (oname, f) in enumerate(others.items()):
            ax.plot(t, np.where(e, f[:, j], np.nan), lw=1.0, ls=("--", ":", "-.")[k % 3], label=oname,
                    color=LINE_COLOURS.get(oname, f"C{(k + 4) % 10}"))
        v = np.where(e, fill[:, j], np.nan)
        s = np.where(e, std[:, j], np.nan)
        line, = ax.plot(t, v, lw=1.3, color="tab:red", label=name)
        ax.fill_between(t, v - 2 * s, v + 2 * s, color=line.get_color(), alpha=0.22, lw=0, label=f"{name} +-2 std")
        ax.set_ylabel(f"{channels[j]} (deg)", fontsize=8)
    axes[-1, 0].set_xlabel("time (s); grey = markers dropped out (length above each span)")
    if title:
        axes[0, 0].set_title(title, fontsize=9, pad=10)
    h, lab = axes[0, 0].get_legend_handles_labels()
    fig.legend(h, lab, loc="lower center", fontsize=7, ncol=len(lab), frameon=False)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_latency(path: str, runs: dict[str, np.ndarray], title: str = "") -> str:
    """Histogram of round trips (ms, log x) of one or more runs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    allv = np.concatenate([v for v in runs.values() if v.size] or [np.array([0.1])])
    lo, hi = max(1e-3, float(allv.min())), max(float(allv.max()), 1e-2)
    bins = np.geomspace(lo * 0.9, hi * 1.1, 60).tolist()
    for name, v in runs.items():
        if v.size:
            p99 = np.percentile(v, 99)
            ax.hist(v, bins=bins, histtype="step", lw=1.4, label=f"{name} (n={v.size}, p50 {np.median(v):.3f}, p99 {p99:.3f} ms)")
    ax.set_xscale("log")
    ax.set_xlabel("round trip (ms)")
    ax.set_ylabel("frames")
    ax.legend(fontsize=7)
    if title:
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_json(path: str, obj: Any) -> None:
    with open(path, "w") as fh:
        json.dump(obj, fh, indent=2, sort_keys=True, default=_json_default)
        fh.write("\n")


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
