"""Scheduler -> encode for a bundle waiting as one block (daemon/blockpath.py): the tick of
daemon/tick.py for the usual case of a studio's bundle, as arrays.

The frames are answered exactly as the row path answers them (the same fills, drops, order,
counters and session states; tests/test_daemon_blockpath.py compares the two on fuzzed bundles):
the streams in the table's order, the model stepped on the block's (n, C) rows, the replies'
angles, masks and deviations built as (n, C) arrays and encoded at once, one map per frame
straight from them (no fill message object), the bundle's replies packed in one pass and sent
as one message.  A tick the array path does not cover (frames already overdue when the tick
begins, more streams than ``max_batch``, a model's fills that do not stack) declines before it
changes anything, or hands its results to the row path's tail.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from daemon import blockpath, wire
from daemon.blockpath import BlockWait
from daemon.parts import Parts
from daemon.session import Pending, Session

_NONE: dict[str, Any] = {}


class BlockTick(Parts):
    """The serving half of the daemon for a block (mixed into daemon.tick.Tick)."""

    def _serve_block(self, bw: BlockWait) -> bool:
        """Serve the one block waiting; False (nothing changed): the row path serves it."""
        plan, sessions, sched = bw.plan, self.sessions, self.sched
        S = plan.table
        n = len(S)
        if plan.gen != sessions.gen or n > sched.max_batch:
            return False
        t0 = self.clock()
        arrived = bw.arrived
        late = [s.late_streak for s in S]
        if self._drop_overdue and True in sched.overdue([arrived] * n, t0, late):
            return False  # some are overdue before the step: the row path picks which
        sessions.blocks.clear()
        sessions.block_served += 1
        block, rows = bw.block, plan.perm
        seqs_all = block.seqs
        seqs = [seqs_all[i] for i in rows]
        mf, mo = blockpath.inputs(block, rows)
        sent = mo
        model = plan.model
        styles: list[Any] | None = None
        phases: list[Any] | None = None
        held: list[bool] | None = None
        if model.passthrough:
            sched.passthrough_rows(model, S, seqs, mf)
            # answered oldest first, then the streams dropped `overdue` most (Tick._serve's sort)
            order = sorted(range(n), key=lambda k: -S[k].late_streak) if any(late) else list(range(n))
            statuses = None
            frames, std, filled = mf[order], np.zeros((n, mf.shape[1])), np.zeros((n, mf.shape[1]), bool)
        else:
            got = sched.run_rows(model, S, seqs, arrived, mf, mo)
            if n > 1:
                got.sort(key=_late)
            order = [g[0] for g in got]
            fills = [g[1][1] for g in got]
            statuses = [g[1][2] for g in got]
            try:
                frames, std, filled = _stack(fills, n, mf.shape[1])
            except Exception:  # noqa: BLE001 - fills that do not stack: the row path's tail names the one
                for k in order:
                    S[k].pending = _pending(bw, rows[k])
                self._answer([g[1] for g in got], t0)
                return True
            exs = [f.extras or _NONE for f in fills]
            styles, phases, held = _styles([ex.get("style") for ex in exs], n), [ex.get("phase") for ex in exs], \
                [f.degraded for f in fills]
        so = [S[k] for k in order]
        qo = [seqs[k] for k in order]
        ro = [rows[k] for k in order]
        self.metrics.inc("ticks")
        self.metrics.step_time(self.clock() - t0)
        t1 = self.clock()
        gaps = [0 if s.last_seq is None else max(0, q - s.last_seq - 1) for s, q in zip(so, qo)]
        _, ab, fb, sb = blockpath.fill_maps(block, ro, frames, std, filled, sent[order])
        t1e = self.clock()
        now = self.clock()
        budget, sent_at, drop = sched.budget_s, sched.sent_at, self._drop_overdue
        proc_us = int((now - arrived) * 1e6)
        stamps = block.stamps
        name = S[0].model_name
        origin = bw.origin
        maps: list[dict[str, Any]] = []
        out: list[Session] = []
        degraded = last_r = 0
        for k in range(n):
            s, q = so[k], qo[k]
            if drop and sent_at(now, n - k, n) - arrived > budget:
                # the step ran longer than planned: this fill would leave over budget (Tick._answer)
                self.metrics.inc("overdue_after_step")
                self._conflated.extend(sessions.overdue_seq(s, q, origin))
                continue
            status = "passthrough" if statuses is None else statuses[k]
            deg = status == "degraded"
            s.filled_seq(q, deg)
            m = {"v": 1, "type": "fill", "stream": s.sid, "seq": q, "t": stamps[ro[k]], "angles": ab[k],
                 "filled": fb[k], "std": sb[k], "status": status, "model": name, "proc_us": proc_us}
            if styles is not None and styles[k] is not None:
                m["style"] = styles[k]
            if phases is not None and (ph := phases[k]) is not None and math.isfinite(ph):
                m["phase"] = float(ph)
            if gaps[k]:
                m["gap"] = gaps[k]
            if deg:
                degraded += 1
                self.metrics.inc("degraded_held" if held is not None and held[k] else "degraded_iterations")
            maps.append(m)
            out.append(s)
            last_r = ro[k]
        if degraded:
            self.metrics.inc("degraded", degraded)
        if out:
            self.metrics.inc("frames_out", len(out))
        self._send_fills(origin, maps)
        te = self.clock()
        self._send_held(len(out))
        if out and self.prewarm.on:
            self.prewarm.served(out[-1], _frame(block, last_r), arrived, sched)
        t2 = self.clock()
        sched.observe_replies(n, te - t1e, t2 - t1)
        lat = self.metrics.latency
        wait = t2 - arrived
        for _ in out:
            lat(wait)
        if out and wait > budget:
            for s in out:
                s.count("over_budget")
            self.metrics.inc("over_budget", len(out))
        return True


def _late(g: tuple[int, tuple[Session, Any, str]]) -> int:
    return -g[1][0].late_streak


def _stack(fills: list[Any], n: int, C: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    frames = np.array([f.frame for f in fills], dtype=np.float32)
    std = np.array([f.std for f in fills], dtype=np.float32)
    filled = np.array([f.filled for f in fills], dtype=bool)
    if not (frames.shape == std.shape == filled.shape == (n, C)):
        raise ValueError(f"fills do not stack to ({n}, {C})")
    return frames, std, filled


def _styles(styles: list[Any], n: int) -> list[Any]:
    """Each row's style posterior as the bytes daemon/pack.py writes (None: none)."""
    if all(st is not None for st in styles):  # (not `None in`: == on an array is elementwise)
        try:  # every stream has one: an (n, K) float32 array, a row each
            a = np.array(styles, dtype=np.float32).reshape(n, -1)
            return [a[i].tobytes() for i in range(n)]
        except ValueError:
            pass
    return [None if st is None else np.asarray(st, np.float32).ravel().tobytes() for st in styles]


def _frame(block: Any, r: int) -> wire.Frame:
    return wire.Frame(block.sids[r], block.seqs[r], block.stamps[r], block.values[r],
                      None if block.mask is None else block.mask[r])


def _pending(bw: BlockWait, r: int) -> Pending:
    return Pending(_frame(bw.block, r), bw.origin, bw.arrived)
