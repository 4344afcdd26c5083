"""Scheduler -> tick for a bundle served as arrays (daemon/tickblock.py): one group of a bundle's
streams planned and stepped by :meth:`Model.step_block`, the fills coming back as (n, C) arrays,
the style posteriors and phases as arrays where the model writes them so (the HLM's one-call
step), with no Fill per stream.  Everything else :meth:`Scheduler._step` does for a group is done
the same way (gap restarts, prediction rounds, a model error passing the frames through, the cost
fit, the sessions' ``stepped``); a plan that holds some streams goes through the row path's
``_hold_many`` and ``_step`` and its Fills are stacked by the caller."""
from __future__ import annotations

from typing import Any

import numpy as np

from daemon.scheduler import Scheduler, StepPlan, levels_of, predict_gaps
from daemon.session import Session, stepped_rows
from lacuna.filler import BlockFill, Fill, FillsDoNotStack, Model

Got = tuple[list[int], BlockFill | list[Fill], list[str]]
_F64 = np.dtype(np.float64)


def run_block(sched: Scheduler, model: Model, group: list[Session], seqs: list[int], arrived: float,
              frames: np.ndarray, observed: np.ndarray) -> Got:
    """:meth:`Scheduler.run` for one group (at most max_batch streams) of a bundle served as
    arrays: the streams' frames are ``seqs`` and the (n, C) model inputs.  Returns (rows, fills,
    statuses): the group rows answered, in the order :meth:`Scheduler.run` gives them, their fills
    in that order (a BlockFill, or Fills: a plan that holds streams, or fills that do not stack)
    and a status each."""
    # each stream's gap to its frame (Scheduler._gap), once for the plan and the step: a live
    # tick runs this cold, where every pass over the streams costs (bench/notebook/hlm64-7.md)
    gaps = sched.gaps(group, seqs)
    plan = sched.plan(model, group, sched.clock(), arrived, seqs, gaps)
    if not plan.hold:
        return _step(sched, model, plan, seqs, frames, observed, gaps)
    pos = {id(s): i for i, s in enumerate(group)}
    idx = [pos[id(s)] for s in plan.hold]
    t0 = sched.clock()
    got = sched._hold_many(plan.hold, ([seqs[i] for i in idx], frames[idx], observed[idx]))
    sched.hold_cost.observe(len(plan.hold), sched.clock() - t0)
    if plan.step:
        ids = [pos[id(s)] for s in plan.step]
        got.extend(sched._step(model, plan, ([seqs[i] for i in ids], frames[ids], observed[ids])))
        idx.extend(ids)
    return idx, [g[1] for g in got], [g[2] for g in got]


def _step(sched: Scheduler, model: Model, plan: StepPlan, seqs: list[int], frames: np.ndarray,
          observed: np.ndarray, gaps: list[int]) -> Got:
    """:meth:`Scheduler._step` of a whole group (``plan.step``, in the group's order) on rows;
    ``gaps``: each stream's gap to its frame."""
    group = plan.step
    n = len(group)
    if max(gaps, default=0) > sched.max_gap:  # (else no stream restarts: the gaps stay)
        gaps = sched._restart_gaps(group, seqs)
    C = group[0].mapping.n_model
    level = plan.iterations if plan.iterations != levels_of(model)[0] else None  # (None: full quality)
    t0 = sched.clock()
    fills: list[Fill] | None = None
    try:
        predict_gaps(model, group, gaps, C, level)   # frames that never arrived
        states: list[Any] = [s.state for s in group]
        try:
            got: BlockFill | None = model.step_block(states, frames, observed, level)
        except FillsDoNotStack as e:  # (stepped: answered by the row path's tail, which names the bad one)
            got, fills = None, e.fills
    except Exception as e:  # noqa: BLE001 - a model bug must not stop the daemon: pass the frames through
        sched.step_errors += 1
        sched.last_error = f"{type(e).__name__}: {e}"[:300]
        for s in group:
            s.restart()
        return list(range(n)), BlockFill(np.array(frames), np.zeros((n, C)), np.zeros((n, C), bool)), ["passthrough"] * n
    sched.last_step[id(model)] = sched.clock()
    dt = sched.clock() - t0
    sched.cost(model, plan.iterations).observe(n, dt / (1 + max(gaps, default=0)))
    status = "passthrough" if model.passthrough else ("degraded" if plan.degraded else "ok")
    if got is None:
        assert fills is not None
        for s, fill, q in zip(group, fills, seqs):
            s.stepped(fill.frame, q)
        return list(range(n)), fills, [status] * n
    if type(got.frame) is not np.ndarray or got.frame.dtype != _F64:  # (a model's own frame type: the call only where needed)
        got.frame = np.asarray(got.frame, dtype=np.float64)
    stepped_rows(group, got.frame, seqs)
    return list(range(n)), got, [status] * n
