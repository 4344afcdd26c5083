"""Per-principal budgets for requests whose cost does not depend on the frame rate.

A ``hello`` (up to 4096 channel names to check and map), a ``status`` and ``list-models`` (a
reply built from the daemon's tables) and a ``reload`` cost the serving thread far more than
a frame; a peer sending them as fast as it can could take the thread from everyone else.
Each principal (connection, CURVE key, OSC source: daemon/session.py ``principal``) has a
token bucket of cost units: a hello costs HELLO_COST and, before it is decoded, one unit per
64 channel names beyond the first 64 (checking and mapping them is the cost); a control
request CONTROL_COST.  ``RATE`` units a second on average, bursts of ``BURST``; beyond it a
request is refused ``rate_limited`` (counted) at the cost of a dictionary look-up.  The table of
buckets is bounded (``MAX_KEYS``; the least recently seen principal is forgotten first, which
only ever gives it a full bucket back).  Refills run on the daemon's clock (``now``), never
wall time read here.
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Any

RATE = 1000.0  # cost units a second per principal, sustained (~15 hellos of 4096 names, ~125 controls)
BURST = 2048.0  # (a capture system opening 1024 streams on one connection: 1024 hellos at once)
HELLO_COST = 1.0
CONTROL_COST = 8.0  # a status, list-models or reload
MAX_KEYS = 4096


def names_cost(m: dict[str, Any]) -> float:
    """Units an unpacked hello map is charged before decoding: one per 64 names past the first 64."""
    ch = m.get("channels")
    n = len(ch) if type(ch) is list else 0
    return (n - 64) / 64.0 if n > 64 else 0.0


class Budget:
    def __init__(self, rate: float = RATE, burst: float = BURST, max_keys: int = MAX_KEYS):
        self.rate, self.burst, self.max_keys = rate, burst, max_keys
        self._b: OrderedDict[Any, list[float]] = OrderedDict()  # principal -> [tokens, last refill]
        self.refused = 0

    def allow(self, who: Any, now: float, units: float = 1.0) -> bool:
        """Charge ``units`` to ``who`` at ``now`` (the daemon's clock, seconds: the one its
        expiry and overdue checks read, so a test's clock moves the refill too)."""
        b = self._b.get(who)
        if b is None:
            if len(self._b) >= self.max_keys:
                self._b.popitem(last=False)
            b = self._b[who] = [self.burst, now]
        else:
            self._b.move_to_end(who)
            b[0] = min(self.burst, b[0] + (now - b[1]) * self.rate)
            b[1] = now
        if b[0] >= units:
            b[0] -= units
            return True
        self.refused += 1
        return False
