"""A regular bundle through session -> scheduler -> encode as arrays (issue 19's vectorised path).

A capture system that tracks several performers sends one ``frames`` bundle per capture instant,
the same streams in the same order every time.  daemon/block.py reads such a bundle as a
:class:`FrameBlock` ((n, C) values and mask); this module takes the block into its streams'
sessions and, in daemon/tick.py, serves it, without a ``Frame``, a ``Pending`` or a fill
message object per frame:

* :func:`plan_for` checks once per set of streams and sender (cached until the session table
  changes: ``SessionTable.gen``) that every stream is open, owned by the sender, of the
  bundle's width, sends the model's own channels in its order, asked for no positions, and
  that all share one model; it keeps the sessions in the bundle's order and the permutation to the table's order
  (the order the row path serves them in);
* :func:`take` does what ``SessionTable.frame`` does for each frame (activity, the delivery
  baseline and ``waited``, ``frames_in``), the sequence checks at once, and leaves the block
  waiting as one (``SessionTable.blocks``) instead of n pending slots;
* a bundle of the same streams, newer, while one waits (a daemon behind: two in one turn)
  supersedes it as one: its frames are answered ``conflated`` as the row path answers them;
* anything the array path does not cover (a late or duplicate frame, a frame of a stream that
  already has one waiting otherwise, any other request touching those sessions) makes the block become the n pending slots it stands for
  (``BlockWait.to_pending``, via ``SessionTable.materialize``) before the row path goes on, so
  every answer and every state is the one the row path gives (tests/test_daemon_wire_block.py).
"""
from __future__ import annotations

import operator
from dataclasses import dataclass
from typing import Any

import numpy as np

from daemon.schema import Drop, FrameBlock
from daemon.session import Origin, Pending, Session
from lacuna.filler import Model

PLANS_MAX = 16  # sets of streams whose checks are kept (a studio sends one or a few)
_GT = operator.gt


@dataclass(eq=False)
class BlockPlan:
    """What :func:`plan_for` checked for one bundle's list of streams."""

    key: tuple[str, ...]
    gen: int  # SessionTable.gen when checked
    who: Any  # the sender it was checked for (the owner of every stream)
    sessions: list[Session]  # in the bundle's order
    perm: list[int]  # bundle rows in the table's order
    ident: bool  # perm is 0..n-1 (the studio sends its streams in the order it opened them)
    table: list[Session]  # the sessions in the table's order
    model: Model
    width: int


@dataclass(eq=False)
class BlockWait:
    """A bundle's frames waiting as one: what the n pending slots would hold."""

    plan: BlockPlan
    block: FrameBlock
    origin: Origin
    arrived: float

    def to_pending(self, waiting: dict[int, Session]) -> None:
        """Become the n pending slots (and ``waiting`` entries) the row path would have made."""
        for s, f in zip(self.plan.sessions, self.block.frames()):
            s.pending = Pending(f, self.origin, self.arrived)
            waiting[id(s)] = s


def plan_for(table: Any, block: FrameBlock, who: Any) -> BlockPlan | None:
    """The checked plan for ``block``'s streams (cached), or None: the row path takes it."""
    key = tuple(block.sids)
    plans: dict[tuple[str, ...], BlockPlan] = table.block_plans
    plan = plans.get(key)
    if plan is not None and plan.gen == table.gen and plan.who == who:
        return plan
    sessions = table.sessions
    width = block.values.shape[1]
    got: list[Session] = []
    for sid in key:
        s = sessions.get(sid)
        if s is None or s.owner != who or who is None or s.fk is not None:
            return None
        mp = s.mapping
        if not mp.identity or mp.n_in != width:
            return None
        got.append(s)
    model = got[0].model
    if len(set(key)) != len(key) or any(s.model is not model for s in got):
        return None
    perm = sorted(range(len(got)), key=lambda i: got[i].order)
    plan = BlockPlan(key, table.gen, who, got, perm, perm == list(range(len(got))), [got[i] for i in perm], model, width)
    if len(plans) >= PLANS_MAX:
        plans.clear()
    plans[key] = plan
    return plan


def take(table: Any, block: FrameBlock, origin: Origin, arrived: float, who: Any) -> list[Any] | None:
    """Take a bundle's frames into their sessions as one block, if the array path covers it
    (see the module's docstring); returns the answers owed now: the ``conflated`` drops of the
    frames of a bundle waiting that this one supersedes (a daemon behind: two bundles in one
    turn), else none.  None (nothing changed): the row path takes them."""
    if table.waiting or not table.block_path or len(table.blocks) > 1:
        return None
    plan = plan_for(table, block, who)
    if plan is None:
        return None
    prev: BlockWait | None = table.blocks[0] if table.blocks else None
    if prev is not None and (prev.plan is not plan or not all(map(_GT, block.seqs, prev.block.seqs))):
        return None  # another set of streams, or a frame not newer than the one waiting
    S = plan.sessions
    lasts = [s.last_seq for s in S]
    if None in lasts:  # a stream's first frame (after its hello): any seq opens the numbering
        if not all(last is None or q > last for q, last in zip(block.seqs, lasts)):
            return None
    elif not all(map(_GT, block.seqs, lasts)):  # type: ignore[arg-type]
        return None  # a late or duplicate frame: answered by the row path
    now = table.clock()
    mte = table.recent.move_to_end
    for s, t in zip(S, block.stamps):
        s.last_active = now
        mte(s.sid)
        s.counts["frames_in"] += 1
        if s.delivered(arrived - t):  # did it wait on its way (as SessionTable.frame asks)
            table.count("frames_waited", s.sid)
    out: list[Any] = []
    if prev is not None:  # each waiting frame superseded, as SessionTable.frame conflates it
        po = prev.origin
        for s, q in zip(S, prev.block.seqs):
            s.counts["dropped_conflated"] += 1
            table.count("dropped_conflated", s.sid)
            out.append((po, Drop(s.sid, q, "conflated")))
        table.blocks.clear()
    table.blocks.append(BlockWait(plan, block, origin, arrived))
    return out


def inputs(block: FrameBlock, rows: list[int] | None) -> tuple[np.ndarray, np.ndarray]:
    """The block's rows (in ``rows`` order; None: as they are) as model inputs: (n, C) float64
    frames, NaN where missing, and (n, C) observed (also what the replies count as sent)."""
    v = block.values if rows is None else block.values[rows]
    m = block.mask
    mo = np.isfinite(v) if m is None else (m if rows is None else m[rows])
    return np.where(mo, v.astype(np.float64), np.nan), mo


def fill_maps(block: FrameBlock, rows: list[int] | None, frames: np.ndarray, std: np.ndarray | None,
              filled: np.ndarray | None, sent: np.ndarray) -> tuple[list[bytes], list[bytes], list[bytes]]:
    """The replies' arrays, encoded at once: (angle bytes, filled bytes, std bytes) per row, as
    :func:`daemon.encode.fill_messages` and :func:`daemon.pack.fill_map` give them.  ``std``
    and ``filled`` None: zero everywhere (a pass-through's), one bytes object for every row."""
    given = block.values if rows is None else block.values[rows]
    angles = np.where(sent, given, frames.astype(np.float32, copy=False))  # observed values exactly as sent
    n, C = angles.shape
    k4 = 4 * C
    ab = angles.tobytes()
    if filled is None or std is None:
        fbs, sbs = [bytes(C)] * n, [bytes(k4)] * n
    else:
        fb, sb = (filled & ~sent).tobytes(), np.ascontiguousarray(std, dtype=np.float32).tobytes()
        fbs, sbs = [fb[i * C:(i + 1) * C] for i in range(n)], [sb[i * k4:(i + 1) * k4] for i in range(n)]
    return [ab[i * k4:(i + 1) * k4] for i in range(n)], fbs, sbs
