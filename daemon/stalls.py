"""Stalls: how much later than it asked the serving loop got to run again.

The loop asks ``poll`` to return by a moment (now + its timeout, or at once when work is
waiting).  If the process is stopped (SIGSTOP, a debugger), starved of CPU or swapped out, it
wakes later than that, and nothing the daemon measured around its own work shows it: a
frame's processing time starts when the frame is read, after the stall.  This counts those
late wake-ups, by how late (over each of THRESHOLDS_S), and keeps the worst; and, since a
stop can also fall inside a turn's work, the turns that took that long from waking to asking
to sleep again.  Frames that
waited on their way in are counted per stream from their capture timestamps (``waited`` in
daemon/session.py).
"""
from __future__ import annotations

import time
from typing import Any

THRESHOLDS_S = (0.004, 0.1, 1.0)


class Stalls:
    def __init__(self) -> None:
        self.over = [0] * len(THRESHOLDS_S)
        self.long = [0] * len(THRESHOLDS_S)
        self.max_s = 0.0
        self.max_turn_s = 0.0
        self.turns = 0
        self._woke_at: float | None = None

    def sleeping(self) -> None:
        """The loop is about to poll again: how long was this turn?"""
        if self._woke_at is None:
            return
        took = time.perf_counter() - self._woke_at
        if took < THRESHOLDS_S[0]:
            return
        self.max_turn_s = max(self.max_turn_s, took)
        for i, t in enumerate(THRESHOLDS_S):
            if took >= t:
                self.long[i] += 1

    def woke(self, due: float) -> None:
        """The loop is running again; it had asked to by ``due`` (perf_counter)."""
        self.turns += 1
        now = self._woke_at = time.perf_counter()
        late = now - due
        if late < THRESHOLDS_S[0]:
            return
        self.max_s = max(self.max_s, late)
        for i, t in enumerate(THRESHOLDS_S):
            if late >= t:
                self.over[i] += 1

    def info(self) -> dict[str, Any]:
        return {"turns": self.turns, "max_stall_ms": round(self.max_s * 1e3, 1),
                "stalls_over": {f"{int(t * 1000)}ms": n for t, n in zip(THRESHOLDS_S, self.over)},
                "max_turn_ms": round(self.max_turn_s * 1e3, 1),
                "long_turns_over": {f"{int(t * 1000)}ms": n for t, n in zip(THRESHOLDS_S, self.long)}}
