"""Scheduler -> encode for a bundle waiting as one block (daemon/blockpath.py): the tick of
daemon/tick.py for the usual case of a studio's bundle, as arrays.

The frames are answered exactly as the row path answers them (the same fills, drops, order,
counters and session states; tests/test_daemon_wire_block.py compares the two on fuzzed bundles):
the streams in the table's order, the model stepped on the block's (n, C) rows, the replies'
angles, masks and deviations built as (n, C) arrays and encoded at once, one map per frame
straight from them (no fill message object), the bundle's replies packed in one pass and sent
as one message.  Frames already overdue when the tick begins (the overload case) are dropped
as Tick._serve drops them and the rest are served as arrays.  A tick the array path does not
cover (more streams than ``max_batch``, a model's fills that do not stack) declines before it
changes anything, or hands its results to the row path's tail.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from daemon import blockpath, stepblock, wire
from daemon.blockpath import BlockWait
from daemon.parts import Parts
from daemon.session import Pending, filled_rows
from lacuna.filler import BlockFill, FillsDoNotStack


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
        block = bw.block
        rows: list[int] | None = None if plan.ident else plan.perm  # (None: the bundle is in the table's order)
        sessions.blocks.clear()
        sessions.block_served += 1
        self.metrics.inc("bundles_as_arrays")  # (status: how many bundles took this path)
        if self._drop_overdue and True in (early := sched.overdue([arrived] * n, t0, late)):
            # the overload case: some frames are overdue before the step (Tick._serve drops
            # them, in the table's order); the rest are served as arrays
            sessions.block_overdue += 1
            origin = bw.origin
            for s, q, x in zip(S, block.seqs if rows is None else [block.seqs[i] for i in rows], early):
                if x:
                    self._conflated.extend(sessions.overdue_seq(s, q, origin))
            keep = [k for k, x in enumerate(early) if not x]
            if not keep:
                return True
            S, late = [S[k] for k in keep], [late[k] for k in keep]
            rows, n = (keep if rows is None else [rows[k] for k in keep]), len(keep)
        seqs = block.seqs if rows is None else [block.seqs[i] for i in rows]
        mf, mo = blockpath.inputs(block, rows)
        model = plan.model
        statuses: list[str] | None = None
        styles: list[Any] | None = None
        phases: list[Any] | None = None
        rowwise = False  # (True: every row has a style's bytes and a finite phase: both go in each map's literal)
        held: list[bool] | None = None
        std: np.ndarray | None = None
        filled: np.ndarray | None = None
        if model.passthrough:
            sched.passthrough_rows(model, S, seqs, mf)
            # answered oldest first, then the streams dropped `overdue` most (Tick._serve's sort)
            order = sorted(range(n), key=lambda k: -S[k].late_streak) if any(late) else None
            frames = mf if order is None else mf[order]
        else:
            idx, got, sts = stepblock.run_block(sched, model, S, seqs, arrived, mf, mo)
            fills = got if isinstance(got, list) else None
            bf: BlockFill | None = None if fills is not None else got  # type: ignore[assignment]
            if fills is not None:  # (held streams, or fills that do not stack)
                try:
                    bf = BlockFill.of(fills, mf.shape[1])
                except FillsDoNotStack:
                    pass
            # answered oldest first, then the streams dropped `overdue` most (Tick._serve's sort)
            pos = sorted(range(n), key=lambda j: -S[idx[j]].late_streak) if n > 1 else [0]
            ident = pos == idx == list(range(n))
            order = None if ident else [idx[j] for j in pos]
            if bf is None:  # fills that do not stack: the row path's tail names the one
                assert fills is not None
                for k in (order or range(n)):
                    S[k].pending = _pending(bw, k if rows is None else rows[k])
                self._answer([(S[idx[j]], fills[j], sts[j]) for j in pos], t0)
                return True
            if ident:
                frames, std, filled, statuses = bf.frame, bf.std, bf.filled, sts
            else:
                frames, std, filled, statuses = bf.frame[pos], bf.std[pos], bf.filled[pos], [sts[j] for j in pos]
            st, phs, dgr = bf.style, bf.phase, bf.degraded
            if isinstance(st, np.ndarray):  # (n, K) posteriors: as the bytes daemon/pack.py writes, a row each
                a = np.ascontiguousarray(st if ident else st[pos], dtype=np.float32).reshape(n, -1)
                yb, k4 = a.tobytes(), 4 * a.shape[1]  # (slices of one bytes object: no array view a row)
                styles = [yb[i * k4:(i + 1) * k4] for i in range(n)]
            elif st is not None:
                styles = _styles(st if ident else [st[j] for j in pos], n)
            if phs is not None:
                phases = (phs if ident else phs[pos]).tolist() if isinstance(phs, np.ndarray) else \
                    (phs if ident else [phs[j] for j in pos])
                rowwise = isinstance(st, np.ndarray) and isinstance(phs, np.ndarray) and bool(np.isfinite(phs).all())
            if dgr is not None:
                held = dgr if ident else [dgr[j] for j in pos]
        if order is None:  # (answer order = table order)
            so, qo, ro, sent = S, seqs, rows, mo
        else:
            so, qo, sent = [S[k] for k in order], [seqs[k] for k in order], mo[order]
            ro = order if rows is None else [rows[k] for k in order]
        self.metrics.inc("ticks")
        self.metrics.step_time(self.clock() - t0)
        t1 = self.clock()
        gaps = [0 if s.last_seq is None else q - s.last_seq - 1 for s, q in zip(so, qo)]  # (None: a first frame)
        ab, fb, sb = blockpath.fill_maps(block, ro, frames, std, filled, sent)
        t1e = self.clock()
        now = self.clock()
        budget, drop, origin = sched.budget_s, self._drop_overdue, bw.origin
        # the step ran longer than planned: fills that would leave over budget are dropped, as
        # Tick._answer checks each (sent_at(now, n - k, place) - arrived > budget): a bundle's
        # replies leave together (place n: true for a prefix of them), a PULL bundle's fills one
        # by one on PUB (place: the fills sent before it, plus one)
        ks: range | list[int] = range(n)
        if drop:
            enc, snd = sched.encode_cost, sched.send_cost
            if len(origin) == 3:
                k0 = 0
                while k0 < n and now + (n - k0) * enc + n * snd - arrived > budget:
                    k0 += 1
                gone: range | list[int] = range(k0)
                ks = range(k0, n)
            else:
                kept: list[int] = []
                gone = []
                for k in range(n):
                    (gone if now + (n - k) * enc + (len(kept) + 1) * snd - arrived > budget else kept).append(k)
                ks = kept
            if gone:
                self.metrics.inc("overdue_after_step", len(gone))
                for k in gone:
                    self._conflated.extend(sessions.overdue_seq(so[k], qo[k], origin))
        whole = len(ks) == n
        out = so if whole else [so[k] for k in ks]
        qk = qo if whole else [qo[k] for k in ks]
        degs = None if statuses is None else [statuses[k] == "degraded" for k in ks]
        filled_rows(out, qk, degs)
        stamps = block.stamps if ro is None else [block.stamps[r] for r in ro]
        proc_us = int((now - arrived) * 1e6)
        name = S[0].model_name
        status = "passthrough"
        cols: list[list[Any]] = [stamps, ab, fb, sb] if whole else [[c[k] for k in ks] for c in (stamps, ab, fb, sb)]
        maps: list[dict[str, Any]]
        one_pass = rowwise and not any(gaps)
        if one_pass:  # (the HLM's bundle: the maps of the loop below, built in one pass)
            assert styles is not None and phases is not None and statuses is not None
            yk, pk = (styles, phases) if whole else ([styles[k] for k in ks], [phases[k] for k in ks])
            maps = [{"v": 1, "type": "fill", "stream": s.sid, "seq": q, "t": t, "angles": a, "filled": f, "std": d,
                     "status": u, "model": name, "proc_us": proc_us, "style": y, "phase": ph}
                    for s, q, t, a, f, d, u, y, ph in zip(out, qk, *cols, statuses if whole else [statuses[k] for k in ks],
                                                          yk, pk)]
        else:
            maps = [
                {"v": 1, "type": "fill", "stream": s.sid, "seq": q, "t": t, "angles": a, "filled": f, "std": d,
                 "status": status if statuses is None else statuses[k], "model": name, "proc_us": proc_us}
                for k, s, q, t, a, f, d in zip(ks, out, qk, *cols)]
        if not one_pass and (styles is not None or phases is not None or any(gaps)):
            for k, m in zip(ks, maps):
                if styles is not None and styles[k] is not None:
                    m["style"] = styles[k]
                if phases is not None and (ph := phases[k]) is not None and math.isfinite(ph):
                    m["phase"] = float(ph)
                if gaps[k] > 0:
                    m["gap"] = gaps[k]
        if degs is not None and True in degs:
            self.metrics.inc("degraded", sum(degs))
            for k, dg in zip(ks, degs):
                if dg:
                    self.metrics.inc("degraded_held" if held is not None and held[k] else "degraded_iterations")
        if out:
            self.metrics.inc("frames_out", len(out))
        self._send_fills(origin, maps)
        te = self.clock()
        self._send_held(len(out))
        # (no rehearsal is planned for a bundle: it would run one stream's row path, not this
        # tick's, and cost the loop an extra wake a tick; live, 64 x 120 Hz, CPU per frame
        # 0.84x pass-through, 0.94x hlm without it, p50 unchanged: bench/notebook/wire-4.md)
        t2 = self.clock()
        sched.observe_replies(n, te - t1e, t2 - t1)
        wait = t2 - arrived
        self.metrics.latencies(wait, len(out))
        if out and wait > budget:
            for s in out:
                s.count("over_budget")
            self.metrics.inc("over_budget", len(out))
        return True


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
