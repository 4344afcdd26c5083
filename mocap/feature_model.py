"""Models that learn in the feature space of ``mocap.representation`` share this plumbing.

A subclass supplies a *core* that works on normalised features, batched over streams:

    core_init(n) -> dict[str, ndarray]             per-stream state, every array (n, ...)
    core_step(state, z, zobs) -> CoreOut           z: (n, F) features, NaN where missing;
                                                    zobs: (n, F) bool.  Updates state in place.

and this class turns it into the Filler seam: raw frames in, representation encode, core step,
decode, exact pass-through of observed channels, commit.

Per-stream state lives batch-shaped in a pool owned by the model (``StatePool``): every stream
holds a row (a *slot*) of each state array, so ``step_batch`` over the streams of a daemon tick
works on views of the pool when their slots are contiguous (the usual case: a stream takes the
lowest free slot) and otherwise gathers and scatters the rows with one fancy index per array,
instead of restacking per-stream arrays every frame.  A core whose large arrays it only reads
and writes by row (the HLM's stream-cycle statistics) names them in ``core_sparse_keys``: those
are never gathered; the core gets the whole pool array and the batch's slots (``rows``) and
indexes them itself, so a tick touches only the rows it needs.  The state must be updated in
place (``state[k][...] = ...``, ``+=``), never by rebinding ``state[k]``.
"""
from __future__ import annotations

import weakref
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lacuna import jit
from lacuna.filler import BlockFill, Fill, FillerState, Model, check_frame
from mocap import fastrepr
from mocap.representation import Representation, ReprState

REPR_ATTRS = ("prev_u", "prev_raw", "prev_yaw", "started", "root_st")


@dataclass
class CoreOut:
    """z: (n, F) completed normalised features; z_std: (n, F) predictive std (0 where observed);
    extras: per-stream dicts (style posterior, phase, ...)."""

    z: np.ndarray
    z_std: np.ndarray
    extras: list[dict[str, Any]] = field(default_factory=list)


class StatePool:
    """Batch-shaped per-stream state of one FeatureModel: each array is (capacity, ...), a stream
    owns one row.  Rows are handed out lowest-free-first and start from the model's initial state
    (``core_init(1)`` and a fresh representation state); capacity doubles when full."""

    def __init__(self, model: FeatureModel):
        self._core0 = model.core_init(1)
        rs = model.representation.new_state(1)
        self._repr0 = {a: getattr(rs, a) for a in REPR_ATTRS}
        self.core: dict[str, np.ndarray] = {}
        self.repr: dict[str, np.ndarray] = {}
        self.capacity = 0
        self._free: list[int] = []
        self._grow(4)

    def _grow(self, cap: int) -> None:
        for store, init in ((self.core, self._core0), (self.repr, self._repr0)):
            for k, v in init.items():
                new = np.repeat(v, cap, axis=0)
                if k in store:
                    new[: self.capacity] = store[k]
                store[k] = new
        self._free = sorted(set(self._free) | set(range(self.capacity, cap)))
        self.capacity = cap

    def acquire(self) -> int:
        if not self._free:
            self._grow(2 * self.capacity)
        slot = self._free.pop(0)
        self.reset(slot)
        return slot

    def reset(self, slot: int) -> None:
        for store, init in ((self.core, self._core0), (self.repr, self._repr0)):
            for k, v in init.items():
                store[k][slot] = v[0]

    def release(self, slot: int) -> None:
        self._free.append(slot)
        self._free.sort()

    @property
    def in_use(self) -> int:
        return self.capacity - len(self._free)


class FeatureModel(Model):
    representation: Representation
    core_sparse_keys: tuple[str, ...] = ()   # state arrays the core indexes by row itself (module doc)

    # ---- hooks ----------------------------------------------------------------------------------
    def core_init(self, n: int) -> dict[str, np.ndarray]:
        raise NotImplementedError

    def core_step(self, state: dict[str, np.ndarray], z: np.ndarray, zobs: np.ndarray,
                  rows: np.ndarray | None = None) -> CoreOut:
        """``rows`` (n,) int: only for a core with ``core_sparse_keys``; the pool rows of the batch,
        which index the arrays named there (those are then the whole pool).  None: every array
        of ``state`` is the batch's own (n, ...).  A core with degradation levels
        (``quality_levels``) also takes ``level=`` (passed only when not None), as an argument:
        the model itself never changes for a step."""
        raise NotImplementedError

    # ---- seam -----------------------------------------------------------------------------------
    @property
    def channels(self) -> list[str]:  # type: ignore[override]
        return self.representation.channels

    @property
    def pool(self) -> StatePool:
        pool = self.__dict__.get("_pool")
        if pool is None:
            pool = self.__dict__["_pool"] = StatePool(self)
        return pool

    def stream(self) -> FeatureStream:
        return FeatureStream(self)

    def step_arrays(self, repr_state: ReprState, core_state: dict[str, np.ndarray],
                    frames: np.ndarray, observed: np.ndarray, rows: np.ndarray | None = None,
                    level: int | None = None) -> tuple[np.ndarray, np.ndarray, list[dict[str, Any]]]:
        """One vectorised step over n streams.  frames, observed: (n, C).  Returns (completed, std, extras).
        ``level`` (not None: one of ``quality_levels()``) goes to ``core_step`` as an argument."""
        # the representation's compiled code (mocap.fastrepr), stream by stream, where it may run:
        # the same arithmetic as ReprState's numpy in two calls instead of about a hundred and fifty
        # (CMU ASF's root convention only: another skeleton's root frame is numpy's, mocap.rootframe)
        rep = self.representation
        compiled = jit.enabled() and (rep.root is None or rep.root_mode != "relative")
        z, zobs = fastrepr.encode(repr_state, frames, observed) if compiled else repr_state.encode(frames, observed)
        kw: dict[str, Any] = {} if rows is None else {"rows": rows}
        if level is not None:
            kw["level"] = level
        out = self.core_step(core_state, z, zobs, **kw)
        if compiled:
            completed, std = fastrepr.finish(repr_state, out.z, out.z_std, frames, observed)
        else:
            completed, std = repr_state.finish(out.z, out.z_std, frames, observed)
        return completed, std, out.extras

    def _views(self, lo: int, hi: int) -> tuple[ReprState, dict[str, np.ndarray]]:
        """The representation and core state of pool rows lo..hi-1, as views (writes go to the pool)."""
        pool = self.pool
        rs = ReprState.of(self.representation, *(pool.repr[a][lo:hi] for a in REPR_ATTRS))
        return rs, {k: v[lo:hi] for k, v in pool.core.items()}

    def step_one(self, slot: int, frame: np.ndarray, observed: np.ndarray) -> Fill | None:
        """Optional: one stream's step (pool row ``slot``; frame (C,) float64, observed (C,) bool)
        in one compiled call, the same arithmetic as ``step_arrays`` on the row's views.  None:
        this core has none here (``step_arrays`` serves)."""
        return None

    def step_rows(self, slots: np.ndarray, frames: np.ndarray, observed: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, list[dict[str, Any]]] | None:
        """Optional: n streams' step (distinct pool rows ``slots`` (n,) int; frames (n, C) float64,
        observed (n, C) bool) in one compiled call on the pool rows in place, the same arithmetic
        as ``step_arrays``.  Returns (completed, std, extras) or None: this core has none here."""
        return None

    def step_rows_arrays(self, slots: np.ndarray, frames: np.ndarray, observed: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None] | None:
        """Optional: :meth:`step_rows` with the extras as arrays: (completed (n, C), std (n, C),
        style posteriors (n, K) or None, phases (n,) or None), or None: this core has none here."""
        return None

    def step_block(self, states: Sequence[FillerState], frames: np.ndarray, observed: np.ndarray,
                   level: int | None = None) -> BlockFill:
        """``step_batch``'s fills as arrays: for n > 1 streams of this model at full quality,
        straight from the core's one-call step (:meth:`step_rows_arrays`), no Fill per stream;
        otherwise ``step_batch``'s Fills stacked (``Model.step_block``)."""
        n = len(states)
        if n > 1 and level is None and all(isinstance(s, FeatureStream) and s.model is self for s in states):
            slots = np.fromiter((s.slot for s in states), dtype=np.intp, count=n)  # type: ignore[attr-defined]
            srt = np.sort(slots)
            if (srt[1:] == srt[:-1]).any():
                raise ValueError("step_batch was given the same stream twice")
            frames = _writable(np.asarray(frames, dtype=np.float64))
            observed = _writable(np.asarray(observed, dtype=bool))
            got = self.step_rows_arrays(slots, frames, observed)
            if got is not None:
                done, std, style, phase = got
                return BlockFill(done, std, ~observed, style, phase)
        return super().step_block(states, frames, observed, level)

    def step_batch(self, states: Sequence[FillerState], frames: np.ndarray, observed: np.ndarray,
                   level: int | None = None) -> list[Fill]:
        """``level`` (None: full quality) is handed to ``core_step``; the model is not changed."""
        mine = [s for s in states if isinstance(s, FeatureStream) and s.model is self]
        if len(mine) != len(states):
            return super().step_batch(states, frames, observed, level)
        frames = _writable(np.asarray(frames, dtype=np.float64))
        observed = _writable(np.asarray(observed, dtype=bool))
        n = len(mine)
        if n == 1:
            # one stream (the usual live case): the core's whole-step call when it has one, else
            # its slot is its own contiguous block
            one = self.step_one(mine[0].slot, frames[0], observed[0]) if level is None else None
            if one is not None:
                return [one]
            lo = mine[0].slot
            rs, cs = self._views(lo, lo + 1)
            done, std, extras = self.step_arrays(rs, cs, np.where(observed, frames, np.nan), observed, level=level)
            return [Fill(done[0], std[0], ~observed[0], extras[0] if extras else {})]
        slots = np.fromiter((s.slot for s in mine), dtype=np.intp, count=n)
        order = np.argsort(slots, kind="stable")
        srt = slots[order]
        if n and (srt[1:] == srt[:-1]).any():
            raise ValueError("step_batch was given the same stream twice")
        got = self.step_rows(slots, frames, observed) if level is None and n else None
        if got is not None:
            # the whole batch in one compiled call on the pool rows, in the caller's order
            done, std, extras = got
            return [Fill(a, b, c, e) for a, b, c, e in zip(done, std, ~observed, extras)]  # (row views, no indexing)
        frames, observed = frames[order], observed[order]
        given = np.where(observed, frames, np.nan)
        pool = self.pool
        if n and srt[-1] - srt[0] == n - 1:
            # contiguous slots: step the pool in place through views, nothing copied
            rs, cs = self._views(int(srt[0]), int(srt[-1]) + 1)
            done, std, extras = self.step_arrays(rs, cs, given, observed, level=level)
        else:
            rs = ReprState.of(self.representation, *(pool.repr[a][srt] for a in REPR_ATTRS))
            sparse = set(self.core_sparse_keys)
            cs = {k: (v if k in sparse else v[srt]) for k, v in pool.core.items()}
            done, std, extras = self.step_arrays(rs, cs, given, observed, rows=srt if sparse else None, level=level)
            for a in REPR_ATTRS:
                pool.repr[a][srt] = getattr(rs, a)
            for k, v in cs.items():
                if k not in sparse:
                    pool.core[k][srt] = v
        fills: list[Fill] = [None] * n  # type: ignore[list-item]
        missing = ~observed  # (one array op, a row view each: not one per stream)
        for j, i in enumerate(order.tolist()):
            fills[i] = Fill(done[j], std[j], missing[j], extras[j] if extras else {})
        return fills


def _writable(a: np.ndarray) -> np.ndarray:
    """a, or a copy where it is read-only (a frame decoded from the wire): the compiled steps are
    compiled for writable arrays, and a read-only one would compile a second kernel in the live
    path (seconds, once per install)."""
    return a if a.flags.writeable else a.copy()


class FeatureStream(FillerState):
    """One stream of a FeatureModel: a slot of the model's state pool, released when the stream
    is garbage-collected.  ``repr_state`` and ``core_state`` are views of that slot (n = 1)."""

    def __init__(self, model: FeatureModel):
        self.model = model
        pool = model.pool
        self.slot = pool.acquire()
        weakref.finalize(self, pool.release, self.slot)

    @property
    def repr_state(self) -> ReprState:
        return self.model._views(self.slot, self.slot + 1)[0]

    @property
    def core_state(self) -> dict[str, np.ndarray]:
        return self.model._views(self.slot, self.slot + 1)[1]

    def step(self, frame: np.ndarray | None, observed: np.ndarray | None = None) -> Fill:
        f, obs = check_frame(frame, observed, self.model.n_channels)
        rs, cs = self.model._views(self.slot, self.slot + 1)
        done, std, extras = self.model.step_arrays(rs, cs, f[None], obs[None])
        return Fill(done[0], std[0], ~obs, extras[0] if extras else {})
