"""The scheduler: one batched Filler step per model over the newest frame of every stream.

Each tick takes every session with a pending frame (at most one per stream: the session's
pending slot conflates), groups them by model and steps each group through
``model.step_batch``.  Before stepping it compares an estimate of the step's cost with the time
left before the oldest frame's budget runs out and, if it would overrun, degrades:

1. a cheaper level, where the model offers some (``Model.quality_levels()``: for
   crbm.filler.CRBMModel K, K/2, K/4, ..., 1 Gibbs iterations), passed to that one step
   (``step_batch(..., level=k)``): the model itself is never changed;
2. hold-last-value for the streams that still do not fit (the ones held most recently go
   first next time, so no stream starves).

Replies from a degraded step carry status ``degraded``.  Cost estimates are learned online
per (model, level): step time ~ a + b * n_streams, fitted by exponentially discounted least
squares over recent steps and seeded by a warm-up step when a model is loaded.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from daemon.encode import STACK_MIN, fill_message, fill_messages, model_inputs
from daemon.session import Session, stepped_rows
from lacuna.filler import Fill, Model

SAFETY = 1.25  # multiply cost estimates: better to degrade a little early than overrun
DISCOUNT = 0.97  # per observation, for the cost fit
PROBE_S = 1.0  # seconds: a model held on every stream gets one real step this often
OUTLIER = 4.0  # clip a cost observation at this multiple of the current fit
REPLY_COST_S = 30e-6  # first guess of encode+send per reply, refined online
HOLD_COST_S = 20e-6  # per stream, what hold-last-value costs in the session (numpy overhead)


class CostModel:
    """Step time ~ a + b * n, by discounted least squares (falls back to b = t / n)."""

    def __init__(self) -> None:
        # sum w, sum w n, sum w n^2, sum w t, sum w n t (plain floats: this runs every tick, and
        # numpy scalars cost more than the arithmetic)
        self.s = [0.0, 0.0, 0.0, 0.0, 0.0]
        self.seen = False

    def observe(self, n: int, t: float) -> None:
        if self.seen:
            # one step stretched by the OS (preemption on a busy machine) must not make the
            # scheduler degrade for the next hundred frames: clip outliers to OUTLIER x the fit;
            # a model that really got slower still moves the fit by that factor per step
            a, b = self.coef()
            t = min(t, OUTLIER * max(a + b * n, 1e-6))
        w, sn, snn, st, snt = self.s
        d = DISCOUNT
        self.s = [d * w + 1.0, d * sn + n, d * snn + n * n, d * st + t, d * snt + n * t]
        self.seen = True

    def coef(self) -> tuple[float, float]:
        w, sn, snn, st, snt = self.s
        if w <= 0:
            return 0.0, 0.0
        det = w * snn - sn * sn
        if det > 1e-9 * max(w * snn, 1e-30):
            b = (w * snt - sn * st) / det
            a = (st - b * sn) / w
            if a >= 0 and b >= 0:
                return a, b
        # all steps had (nearly) the same n, or a negative coefficient: cost proportional to n
        return 0.0, st / max(sn, 1e-12)

    def estimate(self, n: int, rounds: int = 1) -> float:
        a, b = self.coef()
        return SAFETY * rounds * (a + b * n)


@dataclass
class StepPlan:
    """What one group gets: level 0 = as asked; ``iterations`` = the Gibbs knob used."""

    step: list[Session]
    hold: list[Session]
    iterations: int | None
    degraded: bool


def levels_of(model: Model) -> list[int | None]:
    """Cost levels a model offers, full quality first: [None] (none) or, for a CRBM, [K, K/2,
    ..., 1] Gibbs iterations (``Model.quality_levels``)."""
    return model.quality_levels()


def _step_batch(model: Model, states: list[Any], frames: np.ndarray, observed: np.ndarray,
                level: int | None) -> list[Fill]:
    """``model.step_batch`` at ``level`` (None: full quality, called as every other caller does)."""
    if level is None:
        return model.step_batch(states, frames, observed)
    return model.step_batch(states, frames, observed, level=level)


def predict_gaps(model: Model, group: list[Session], gaps: list[int], C: int, level: int | None) -> None:
    """The frames that never arrived before each stream's frame (``gaps[i]`` of them): prediction
    steps with every channel missing, batched by round; the row path and the block path both."""
    for r in range(max(gaps, default=0)):
        who = [s for s, g in zip(group, gaps) if g > r]
        _step_batch(model, [s.state for s in who], np.full((len(who), C), np.nan), np.zeros((len(who), C), bool), level)
        for s in who:
            s.count("predicted")


Rows = tuple[list[int], np.ndarray, np.ndarray]  # (seqs, (n, C) frames, (n, C) observed) of a bundle's streams


class Scheduler:
    def __init__(self, budget_ms: float, max_gap: int, max_batch: int, clock: Callable[[], float] = time.perf_counter):
        self.clock = clock  # the daemon's clock: plans against deadlines, step times
        self.budget_s = budget_ms / 1000.0
        self.max_gap = max_gap
        self.max_batch = max_batch
        self.costs: dict[tuple[int, int | None], CostModel] = {}
        self.reply_cost = REPLY_COST_S
        # the same in two parts: building and encoding a reply, and sending it (a tick's replies
        # are encoded one after another, then sent together, oldest first)
        self.encode_cost = REPLY_COST_S / 3
        self.send_cost = REPLY_COST_S * 2 / 3
        self.hold_cost = CostModel()
        self.last_step: dict[int, float] = {}  # id(model) -> perf_counter of its last real step
        self.probes = 0
        self.step_errors = 0
        self.last_error = ""

    def cost(self, model: Model, level: int | None) -> CostModel:
        key = (id(model), level)
        if key not in self.costs:
            self.costs[key] = CostModel()
        return self.costs[key]

    def forget(self, model: Model) -> None:
        for k in [k for k in self.costs if k[0] == id(model)]:
            del self.costs[k]
        self.last_step.pop(id(model), None)

    @staticmethod
    def _ema(old: float, seen: float) -> float:
        # one send stretched by the OS must not make the next ticks drop everything: clip
        return 0.9 * old + 0.1 * min(seen, OUTLIER * old)

    def observe_replies(self, n: int, encode_s: float, total_s: float) -> None:
        """A tick built and encoded ``n`` replies in ``encode_s`` and had them sent ``total_s``
        after it began."""
        self.reply_cost = self._ema(self.reply_cost, total_s / n)
        self.encode_cost = self._ema(self.encode_cost, encode_s / n)

    def observe_sends(self, n: int, seconds: float) -> None:
        """``n`` answers (fills, drops, errors) went out in ``seconds``: every turn that answers
        anything updates this, so an estimate inflated by one bad moment cannot outlive it."""
        self.send_cost = self._ema(self.send_cost, seconds / n)

    def sent_at(self, now: float, to_encode: int, place: int) -> float:
        """When a reply leaves: after the ``to_encode`` replies still to build (itself included)
        and, once the tick's replies are sent together, after the ``place - 1`` sent before it."""
        return now + to_encode * self.encode_cost + place * self.send_cost

    def overdue(self, arrived: list[float], now: float, late: list[int] | None = None) -> list[bool]:
        """Which of a tick's frames (receipt times, in any order) cannot be answered within the
        budget even at no cost but sending: the tick answers oldest first, so the k-th frame in
        that order leaves k sends after ``now`` at the soonest.  Frames are taken oldest first;
        one that misses its deadline at its place is marked and frees its place for the next.
        Frames read at the same moment (a bundle's) go in order of ``late`` (frames in a row each
        stream had dropped), most first, so the same streams do not lose every time.
        (Only the send cost, which every turn measures, counts here: an estimate that only
        frames let through would refresh could otherwise keep every frame out.)"""
        n = len(arrived)
        budget = self.budget_s
        if min(arrived) + budget >= self.sent_at(now, 0, n):  # the usual case: the oldest makes it at the back
            return [False] * n
        out = [False] * n
        kept = 0
        late = late or [0] * n
        for i in sorted(range(n), key=lambda i: (arrived[i], -late[i])):
            if arrived[i] + budget >= self.sent_at(now, 0, kept + 1):
                kept += 1
            else:
                out[i] = True
        return out

    # ---- planning ---------------------------------------------------------------------------
    def _gap(self, s: Session, seq: int | None = None) -> int:
        """Frames the filter of ``s`` missed before its waiting frame (or frame ``seq``)."""
        if s.model_seq is None:
            return 0
        if seq is None:
            p = s.pending
            assert p is not None
            seq = p.frame.seq
        return seq - s.model_seq - 1

    def gaps(self, group: list[Session], seqs: list[int] | None = None) -> list[int]:
        """:meth:`_gap` of every stream of ``group`` (to its frame of ``seqs``), in one pass (a live
        tick runs this cold, where each call per stream costs: bench/notebook/hlm64-7.md)."""
        if seqs is None:
            return [self._gap(s) for s in group]
        return [0 if s.model_seq is None else q - s.model_seq - 1 for s, q in zip(group, seqs)]

    def plan(self, model: Model, group: list[Session], now: float, arrived: float | None = None,
             seqs: list[int] | None = None, gaps: list[int] | None = None) -> StepPlan:
        """Decide level and which streams step (the rest hold).  Pure apart from reading costs.
        (``arrived``, ``seqs``: the oldest receipt and each stream's frame, for a bundle served
        as arrays, whose frames are in no pending slot; ``gaps``: their :meth:`_gap`, where the
        caller has them.)"""
        if model.passthrough:
            return StepPlan(group, [], None, False)
        if arrived is None:
            arrived = min(s.pending.arrived for s in group)  # type: ignore[union-attr]
        deadline = arrived + self.budget_s
        avail = deadline - now - self.reply_cost * len(group)
        if gaps is None:
            gaps = self.gaps(group, seqs)
        rounds = 1 + min(max(gaps), self.max_gap)  # (the largest of the gaps capped: one pass, no generator)
        levels = levels_of(model)
        # a model about as cheap as holding gains nothing from degrading: frames already late
        # (queued while the daemon was busy) are better served in full
        # (holding's own cost is measured alongside, under the same load as the model's)
        hold = self.hold_cost.estimate(len(group)) if self.hold_cost.seen else HOLD_COST_S * len(group)
        if self.cost(model, levels[0]).estimate(len(group), rounds) <= 2.0 * max(hold, HOLD_COST_S * len(group)):
            return StepPlan(group, [], levels[0], False)
        for lv in levels:
            cm = self.cost(model, lv)
            if not cm.seen or cm.estimate(len(group), rounds) <= avail:
                return StepPlan(group, [], lv, lv != levels[0])
        # even the cheapest level cannot take every stream: step as many as fit, hold the rest
        cm = self.cost(model, levels[-1])
        order = sorted(group, key=lambda s: -s.held_streak)
        n = len(order)
        # (the streams held cost time too: what is left for the step is avail less their hold)
        per_hold = hold / max(len(group), 1)
        while n > 0 and cm.estimate(n, rounds) + per_hold * (len(order) - n) > avail:
            n -= 1
        if n == 0 and now - self.last_step.get(id(model), 0.0) > PROBE_S:
            # estimates only improve when the model runs: without an occasional step a
            # pessimistic estimate (a slow warm-up, a busy spell) would hold every stream
            # forever.  One stream, the longest held, at the cheapest level.
            self.probes += 1
            # a full-quality fill that overran the budget is "ok" (its proc_us shows the
            # overrun); it is "degraded" only when the cheapest level is cheaper than asked
            return StepPlan(order[:1], order[1:], levels[-1], levels[-1] != levels[0])
        # the streams that do step get the cheapest level: degraded only if that is cheaper
        # than asked (the held ones are marked degraded by the hold itself)
        return StepPlan(order[:n], order[n:], levels[-1], levels[-1] != levels[0])

    # ---- stepping ---------------------------------------------------------------------------
    def run(self, groups: dict[Any, tuple[Model, list[Session]]], now: float) -> list[tuple[Session, Fill, str]]:
        """Step every group; returns (session, fill in model space, status) for each pending frame."""
        results: list[tuple[Session, Fill, str]] = []
        for model, sessions in groups.values():
            for i in range(0, len(sessions), self.max_batch):
                chunk = sessions[i : i + self.max_batch]
                plan = self.plan(model, chunk, self.clock())
                if plan.hold:
                    t0 = self.clock()
                    results.extend(self._hold_many(plan.hold))
                    self.hold_cost.observe(len(plan.hold), self.clock() - t0)
                if plan.step:
                    results.extend(self._step(model, plan))
        return results

    def _hold(self, s: Session) -> tuple[Session, Fill, str]:
        p = s.pending
        assert p is not None
        frame, obs = s.to_model(p.frame)
        last = s.last_out if s.last_out is not None else np.full(frame.shape, np.nan)
        return self._held(s, *_hold_rows(frame, obs, last))

    def _hold_many(self, group: list[Session], rows: Rows | None = None) -> list[tuple[Session, Fill, str]]:
        """:meth:`_hold` for every stream of a group, as (n, C) arrays when there are enough
        streams of one width to pay for the stacking (holding is what the daemon does when it
        is short of time: per stream it must cost a few microseconds, not a few dozen).
        ``rows``: (seqs, frames, observed) of a bundle served as arrays."""
        C = group[0].mapping.n_model
        if rows is not None:
            seqs, frames, obs = rows
            last = np.array([np.full(C, np.nan) if s.last_out is None else s.last_out for s in group])
            out, std, filled = _hold_rows(frames, obs, last)
            return [self._held(s, out[i], std[i], filled[i], seqs[i]) for i, s in enumerate(group)]
        if len(group) < STACK_MIN or any(s.last_out is None or s.last_out.shape != (C,) for s in group):
            return [self._hold(s) for s in group]
        frames, obs = model_inputs(group, C)
        out, std, filled = _hold_rows(frames, obs, np.array([s.last_out for s in group]))
        return [self._held(s, out[i], std[i], filled[i]) for i, s in enumerate(group)]

    @staticmethod
    def _held(s: Session, out: np.ndarray, std: np.ndarray, filled: np.ndarray,
              seq: int | None = None) -> tuple[Session, Fill, str]:
        s.held(out, seq)
        return s, Fill(out, std, filled, {}, True), "degraded"

    def passthrough_rows(self, model: Model, group: list[Session], seqs: list[int], frames: np.ndarray) -> None:
        """What daemon.stepblock.run_block does to the streams of a pass-through model (whose fill is the
        frame, NaN where missing: ``frames`` itself), without a fill object per stream."""
        t0 = self.clock()
        gaps = [0 if s.model_seq is None else q - s.model_seq - 1 for s, q in zip(group, seqs)]
        if max(gaps, default=0) > 0:
            if max(gaps) > self.max_gap:
                gaps = self._restart_gaps(group, seqs)
            for s, g in zip(group, gaps):
                if g > 0:
                    s.count("predicted", g)
        self.last_step[id(model)] = self.clock()
        self.cost(model, None).observe(len(group), (self.clock() - t0) / (1 + max(gaps, default=0)))
        stepped_rows(group, frames, seqs)

    def _restart_gaps(self, group: list[Session], seqs: list[int] | None) -> list[int]:
        """Restart the filters too far behind; each stream's gap to its frame."""
        if seqs is None:
            for s in group:
                if s.model_seq is not None and self._gap(s) > self.max_gap:
                    s.gap_restart()
            return self.gaps(group)
        for s, q in zip(group, seqs):
            if s.model_seq is not None and self._gap(s, q) > self.max_gap:
                s.gap_restart()
        return self.gaps(group, seqs)

    def _step(self, model: Model, plan: StepPlan, rows: Rows | None = None) -> list[tuple[Session, Fill, str]]:
        """Step ``plan.step``: their waiting frames, or ``rows`` (seqs, frames, observed) of a
        bundle served as arrays."""
        group = plan.step
        seqs = rows[0] if rows is not None else None
        gaps = self._restart_gaps(group, seqs)
        C = group[0].mapping.n_model
        levels = levels_of(model)
        level = plan.iterations if plan.iterations != levels[0] else None  # (None: full quality)
        t0 = self.clock()
        try:
            predict_gaps(model, group, gaps, C, level)   # frames that never arrived
            mf, mo = model_inputs(group, C) if rows is None else rows[1:]
            fills = _step_batch(model, [s.state for s in group], mf, mo, level)
        except Exception as e:  # noqa: BLE001 - a model bug must not stop the daemon: pass the frames through
            self.step_errors += 1
            self.last_error = f"{type(e).__name__}: {e}"[:300]
            out = []
            for i, s in enumerate(group):
                f = s.to_model(s.pending.frame)[0] if rows is None else np.array(rows[1][i])  # type: ignore[union-attr]
                s.restart()
                out.append((s, Fill(f, np.zeros(C), np.zeros(C, bool)), "passthrough"))
            return out
        self.last_step[id(model)] = self.clock()
        dt = self.clock() - t0
        self.cost(model, plan.iterations).observe(len(group), dt / (1 + max(gaps, default=0)))
        status = "passthrough" if model.passthrough else ("degraded" if plan.degraded else "ok")
        out = []
        for i, (s, fill) in enumerate(zip(group, fills)):
            s.stepped(fill.frame, None if seqs is None else seqs[i])
            out.append((s, fill, status))
        return out

    def warm_up(self, model: Model, n_channels: int, sizes: tuple[int, ...] = (1, 4, 16)) -> None:
        """Seed the cost model (and surface a broken model before it serves): a few throwaway
        steps on all-missing frames of fresh states."""
        if model.passthrough:
            return
        C = n_channels
        lvls = levels_of(model)
        for lv in lvls:
            level = lv if lv != lvls[0] else None
            for n in sizes:
                states = [model.stream() for _ in range(n)]
                # half the channels observed (zeros), like a frame with markers lost: an
                # all-missing frame can take a cheap path and would underestimate the cost
                obs = np.zeros((n, C), bool)
                obs[:, ::2] = True
                frames = np.where(obs, 0.0, np.nan)
                for rep in range(4):
                    t0 = self.clock()
                    fills = _step_batch(model, states, frames, obs, level)
                    if rep >= 2:  # first calls fill caches and lags: keep the steady state
                        self.cost(model, lv).observe(n, self.clock() - t0)
                if len(fills) != n or any(np.shape(f.frame) != (C,) for f in fills):
                    raise ValueError(f"step_batch returned {len(fills)} fills of shape "
                                     f"{np.shape(fills[0].frame) if fills else None} for {n} streams of {C} channels")


def _hold_rows(frame: np.ndarray, obs: np.ndarray, last: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hold-last-value, for one frame (C,) or a stack (n, C): (completed, std, filled)."""
    out = np.where(obs, frame, last)
    filled = ~obs & np.isfinite(last)
    # hold-last-value has no uncertainty estimate: NaN says "unknown", not "certain"
    std = np.where(filled, np.nan, 0.0)
    return out, std, filled


__all__ = ["STACK_MIN", "CostModel", "Scheduler", "StepPlan", "fill_message", "fill_messages", "levels_of", "model_inputs"]
