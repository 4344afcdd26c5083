"""Scheduler -> encode: a tick's fills turned into the ``fill`` messages the wire carries (model
space back to the studio's channels, the frame's own values where observed), and the model
inputs of a group built from the streams' waiting frames, both as (n, C) arrays when a group
is large enough to pay for the stacking."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from daemon import wire
from daemon.session import Session
from lacuna.filler import Fill

STACK_MIN = 4  # streams from which a tick's inputs and replies are built as (n, C) arrays (fewer: row by row is cheaper)


def fill_message(s: Session, fill: Fill, status: str, now: float) -> wire.FillMsg:
    """Model-space fill -> the studio's channel order, as a wire message."""
    p = s.pending
    assert p is not None
    mp = s.mapping
    f = p.frame
    sent = f.observed if f.observed is not None else np.isfinite(f.angles)
    if mp.identity:
        # observed values exactly as sent, whatever the model returned
        angles = np.where(sent, f.angles, np.asarray(fill.frame, np.float32))
        filled = np.asarray(fill.filled) & ~sent
        std = np.asarray(fill.std, np.float32)
    else:
        # channels passed through (the model lacks them) come back as sent where observed, NaN
        # where not: whatever was sent under a mask is not a measurement
        angles = np.where(sent, f.angles, np.float32(np.nan)).astype(np.float32, copy=False)
        filled = np.zeros(mp.n_in, bool)
        std = np.zeros(mp.n_in, np.float32)
        angles[mp.s_idx] = np.asarray(fill.frame)[mp.m_idx]
        filled[mp.s_idx] = np.asarray(fill.filled)[mp.m_idx]
        std[mp.s_idx] = np.asarray(fill.std)[mp.m_idx]
        angles[sent] = f.angles[sent]   # observed values exactly as sent, whatever the model returned
        filled &= ~sent
    ex: dict[str, Any] = fill.extras or {}
    style = ex.get("style")
    phase = ex.get("phase")
    gap = 0 if s.last_seq is None else max(0, f.seq - s.last_seq - 1)
    msg = wire.FillMsg(f.stream, f.seq, f.t, angles, filled, std, status, s.model_name,
                       int((now - p.arrived) * 1e6),
                       None if style is None else np.asarray(style, np.float32).ravel(),
                       None if phase is None or not np.isfinite(phase) else float(phase), gap)
    if s.fk is not None:  # the stream's hello asked for positions
        msg.positions = s.fk(fill.frame, angles)
    return msg


def model_inputs(group: list[Session], C: int) -> tuple[np.ndarray, np.ndarray]:
    """The pending studio frames of a step group -> model space: (n, C) float64 frames (NaN
    where missing) and (n, C) observed masks.  Streams that send the model's own channels in
    its order (the usual case) are stacked in one go; the others are mapped one by one."""
    frames = [s.pending.frame for s in group]  # type: ignore[union-attr]
    if len(group) >= STACK_MIN and all(s.mapping.identity for s in group):
        a = np.array([f.angles for f in frames], dtype=np.float64)
        if all(f.observed is None for f in frames):
            mo = np.isfinite(a)
        else:
            mo = np.array([np.isfinite(f.angles) if f.observed is None else f.observed for f in frames], dtype=bool)
        return np.where(mo, a, np.nan), mo
    mf = np.empty((len(group), C))
    mo = np.empty((len(group), C), bool)
    for i, (s, f) in enumerate(zip(group, frames)):
        mf[i], mo[i] = s.to_model(f)
    return mf, mo


def fill_messages(results: list[tuple[Session, Fill, str]], now: float) -> list[wire.FillMsg | Exception]:
    """:func:`fill_message` for a whole tick, with the streams that need no channel mapping done
    as (n, C) arrays at once.  Each entry is the message, or the exception that made it
    impossible (the daemon answers that stream with an error and keeps serving the rest)."""
    out: list[wire.FillMsg | Exception | None] = [None] * len(results)
    by_width: dict[int, list[int]] = {}
    small = len(results) < STACK_MIN
    for i, (s, fill, status) in enumerate(results):
        if s.mapping.identity and not small:
            by_width.setdefault(s.mapping.n_in, []).append(i)
        else:
            try:
                out[i] = fill_message(s, fill, status, now)
            except Exception as e:  # noqa: BLE001 - reported per stream by the caller
                out[i] = e
    for C, rows in by_width.items():
        try:
            msgs = _identity_fills([results[i] for i in rows], C, now)
        except Exception:  # noqa: BLE001 - some fill does not fit the array: find which, one by one
            msgs = [_fill_message_or_error(*results[i], now) for i in rows]  # type: ignore[misc]
        for i, m in zip(rows, msgs):
            out[i] = m
    return out  # type: ignore[return-value]


def _fill_message_or_error(s: Session, fill: Fill, status: str, now: float) -> wire.FillMsg | Exception:
    try:
        return fill_message(s, fill, status, now)
    except Exception as e:  # noqa: BLE001 - reported per stream by the caller
        return e


def _identity_fills(items: list[tuple[Session, Fill, str]], C: int, now: float) -> list[wire.FillMsg]:
    """fill_message's identity branch over n streams of width C, as array operations."""
    n = len(items)
    fr = [s.pending.frame for s, _, _ in items]  # type: ignore[union-attr]
    given = np.array([f.angles for f in fr], dtype=np.float32)
    sent = np.array([np.isfinite(f.angles) if f.observed is None else f.observed for f in fr], dtype=bool)
    model_out = np.array([fl.frame for _, fl, _ in items], dtype=np.float32)
    std = np.array([fl.std for _, fl, _ in items], dtype=np.float32)
    filled = np.array([fl.filled for _, fl, _ in items], dtype=bool)
    if not (given.shape == sent.shape == model_out.shape == std.shape == filled.shape == (n, C)):
        raise ValueError(f"fills do not stack to ({n}, {C})")
    angles = np.where(sent, given, model_out)  # observed values exactly as sent, whatever the model returned
    filled &= ~sent
    exs = [fl.extras or _NONE for _, fl, _ in items]
    styles: Any = [ex.get("style") for ex in exs]
    if all(st is not None for st in styles):  # (not `None in`: == on an array is elementwise)
        try:  # every stream has a style posterior: one (n, K) float32 array, a row each
            styles = np.array(styles, dtype=np.float32).reshape(n, -1)
        except ValueError:  # posteriors of different lengths (two models' streams): one by one
            styles = [np.asarray(st, np.float32).ravel() for st in styles]
    else:
        styles = [None if st is None else np.asarray(st, np.float32).ravel() for st in styles]
    msgs = []
    for j, (s, fill, status) in enumerate(items):
        f = fr[j]
        phase = exs[j].get("phase")
        msg = wire.FillMsg(f.stream, f.seq, f.t, angles[j], filled[j], std[j], status, s.model_name,
                           int((now - s.pending.arrived) * 1e6),  # type: ignore[union-attr]
                           styles[j], None if phase is None or not math.isfinite(phase) else float(phase),
                           0 if s.last_seq is None else max(0, f.seq - s.last_seq - 1))
        if s.fk is not None:  # the stream's hello asked for positions
            msg.positions = s.fk(fill.frame, angles[j])
        msgs.append(msg)
    return msgs


_NONE: dict[str, Any] = {}
