"""Scheduler -> encode: one tick serves the frames waiting, a batched step per model, and
answers them (fills first, oldest frame first; drops after the fills).

``Tick`` is a part of :class:`daemon.loop.Daemon`; the plan and the step are the scheduler's
(daemon/scheduler.py), the fills' encoding daemon/wire.py's.
"""
from __future__ import annotations

from typing import Any

from daemon import wire
from daemon.encode import fill_messages
from daemon.tickblock import BlockTick


class Tick(BlockTick):
    """The serving half of the daemon (mixed into :class:`daemon.loop.Daemon`)."""

    def _serve(self) -> None:
        blocks = self.sessions.blocks
        if blocks and len(blocks) == 1 and not self.sessions.waiting and self._serve_block(blocks[0]):
            return
        pend = self.sessions.take_waiting()  # (blocks the array path declined become pending slots)
        if not pend:
            return
        t0 = self.clock()
        if self._drop_overdue and len(pend) == 1:  # (a live stream's turn: Scheduler.overdue of one frame)
            if pend[0].pending.arrived + self.sched.budget_s < t0 + self.sched.send_cost:  # type: ignore[union-attr]
                self._conflated.extend(self.sessions.overdue(pend[0]))
                return
        elif self._drop_overdue:
            late = self.sched.overdue([s.pending.arrived for s in pend], t0,  # type: ignore[union-attr]
                                      [s.late_streak for s in pend])
            if True in late:
                # (answered after the fills, as conflated frames are)
                for s, x in zip(pend, late):
                    if x:
                        self._conflated.extend(self.sessions.overdue(s))
                pend = [s for s, x in zip(pend, late) if not x]
                if not pend:
                    return
        groups: dict[tuple[int, int], tuple[Any, list[Any]]] = {}
        for s in pend:
            # by width too: a pass-through "any channels" model serves streams of different
            # widths, and one batch stacks frames of one width
            groups.setdefault((id(s.model), s.mapping.n_model), (s.model, []))[1].append(s)
        results = self.sched.run(groups, t0)
        if len(results) > 1:
            # answered oldest first: the frame that arrived first is the nearest its budget
            # (earliest deadline first), and each reply is a few dozen microseconds of the tick
            results.sort(key=_arrival)
        self._answer(results, t0)

    def _answer(self, results: list[Any], t0: float) -> None:
        """Encode and send a tick's fills (``results`` from the scheduler, in answer order)."""
        self.metrics.inc("ticks")  # frames_out / ticks = the mean batch the scheduler stepped
        self.metrics.step_time(self.clock() - t0)
        t1 = self.clock()
        msgs = fill_messages(results, t1)  # reads s.pending and s.last_seq (for gap)
        t1e = self.clock()
        sent: list[tuple[Any, float]] = []
        n, budget, sent_at = len(results), self.sched.budget_s, self.sched.sent_at
        for k, ((s, fill, status), msg) in enumerate(zip(results, msgs)):
            p = s.pending
            assert p is not None
            if isinstance(msg, Exception):  # a fill the wire cannot carry: answer with an error, keep serving
                s.answered()
                e = msg
                self.log("error", "internal_error", where="fill_message", stream=s.sid, error=f"{type(e).__name__}: {e}"[:300])
                self._refuse(p.origin, "internal", f"{type(e).__name__} while encoding the fill", s.sid, p.frame.seq)
                continue
            now = self.clock()
            # (a bundle's answers leave together, in one `replies`, after the tick's other answers)
            if self._drop_overdue and sent_at(now, n - k, n if len(p.origin) == 3 else len(sent) + 1) - p.arrived > budget:
                # the step ran longer than planned (most often the OS gave the CPU to someone
                # else): by the time this fill would leave it would be over budget.  The filter
                # has taken the frame; the answer is the drop the plan would have made.
                self.metrics.inc("overdue_after_step")
                self._conflated.extend(self.sessions.overdue(s))
                continue
            s.filled(status == "degraded")
            # receipt to this reply's encoding (it is sent with the tick's other replies, below)
            msg.proc_us = int((now - p.arrived) * 1e6)
            if status == "degraded":
                self.metrics.inc("degraded")
                # held (hold-last-value) vs stepped with fewer Gibbs iterations
                self.metrics.inc("degraded_held" if fill.degraded else "degraded_iterations")
            self.metrics.inc("frames_out")
            sent.append((s, p.arrived))
            last = (s, p.frame, p.arrived)
            self._send(p.origin, msg, publish=True)
        te = self.clock()
        self._send_held(len(sent))  # the fills leave now; the turn's drops after them
        if sent and self.prewarm.on:
            self.prewarm.served(*last, self.sched)
        if results:
            t2 = self.clock()
            # what a reply costs (the plan and the overdue checks use it)
            self.sched.observe_replies(n, te - t1e, t2 - t1)
            # receipt to sent: the latency in `status` and the over-budget count (an upper bound
            # for each reply of the tick: all of them had left by t2)
            lat = self.metrics.latency
            over = 0
            for s, arrived in sent:
                lat(t2 - arrived)
                if t2 - arrived > budget:
                    s.count("over_budget")
                    over += 1
            if over:
                self.metrics.inc("over_budget", over)

    def _send_held(self, answers: int | None = None, hold_on: bool = True) -> None:
        """Send the answers held so far (and hold again, or not), timing it for the scheduler:
        per answer (``answers``: how many of them are the caller's to count; a fill also goes
        to PUB, so it is more than one message), else per message sent."""
        net = self.net
        if net is None:
            return
        t0 = self.clock()
        n = net.send_held() if hold_on else net.flush()
        if answers:
            n = answers
        if n:
            self.sched.observe_sends(n, self.clock() - t0)

    def _abandon_pending(self, why: str) -> None:
        """After a failed tick: answer every waiting frame (and every frame set aside as
        superseded) with an error rather than retrying the same failure in a tight loop."""
        todo, self._superseded = self._superseded, []
        try:
            todo_drops, self._conflated = self._conflated, []
            self._deliver(todo_drops)  # (those frames were answered already: drops owed, not errors)
        except Exception:  # noqa: BLE001, S110 - a failing send must not keep the frames below unanswered
            pass
        owed: list[tuple[Any, str, int | None]] = list(self.sessions.abandon())
        # (a chain item: a run of kept heads (seq, t, origin, arrived), or (map, origin, arrived),
        # see daemon/aside.py)
        owed += [(r[2], s.sid, r[0]) if type(item) is list else
                 (item[1], s.sid, k[1] if isinstance(item[0], dict) and (k := wire.frame_key(item[0])) else None)
                 for s, _, _, chain in todo for item in filter(None, chain)
                 for r in (item if type(item) is list else [item])]
        for origin, sid, seq in owed:
            try:
                self._refuse(origin, "internal", why, sid, seq)
            except Exception:  # noqa: BLE001, S110 - the answer itself failing must not stop the loop either
                pass


def _arrival(r: tuple[Any, ...]) -> tuple[float, int]:
    # (frames read together, a bundle's: the streams that were dropped `overdue` most go first)
    return r[0].pending.arrived, -r[0].late_streak

