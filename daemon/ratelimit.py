"""Log rate limiting for floods: a broken or hostile sender must not flood the log.

One warning line per rejected message lets a single misbehaving client write 10^4 lines a
second; journald then rate-limits the *whole service* (by default 10,000 lines per 30 s) and
drops the lines that matter (a refused reload, an expired stream) together with the noise, and
the JSON encoding of every line is CPU the daemon owes to the well-formed streams.

:class:`EventLimiter` lets the first ``burst`` events of each key (the rejection reason) through
per ``window_s`` and counts the rest; :meth:`flush` returns, once per ended window, how many
were held back per key, for one summary line.  The counters in `lacuna status` stay exact:
only log lines are limited.
"""
from __future__ import annotations

import time
from typing import Callable

BURST = 20  # log lines per key per window
WINDOW_S = 5.0


class EventLimiter:
    """``allow(key)`` -> bool; ``flush()`` -> [(key, suppressed count)] for ended windows."""

    def __init__(self, burst: int = BURST, window_s: float = WINDOW_S, clock: Callable[[], float] = time.monotonic):
        if burst < 1 or window_s <= 0:
            raise ValueError(f"burst must be >= 1 and window_s > 0 (got {burst}, {window_s})")
        self.burst, self.window_s, self.clock = burst, window_s, clock
        self._start = clock()
        self._seen: dict[str, int] = {}
        self._ended: dict[str, int] = {}  # suppressed in ended windows, not yet flushed
        self.suppressed_total = 0

    def _roll(self, now: float) -> None:
        if now - self._start < self.window_s:
            return
        for k, n in self._seen.items():
            if n > self.burst:
                self._ended[k] = self._ended.get(k, 0) + n - self.burst
        self._seen = {}
        self._start = now

    def allow(self, key: str) -> bool:
        self._roll(self.clock())
        n = self._seen.get(key, 0) + 1
        self._seen[key] = n
        if n <= self.burst:
            return True
        self.suppressed_total += 1
        return False

    def flush(self) -> list[tuple[str, int]]:
        """Suppressed counts of the windows that ended since the last flush (empty while one runs)."""
        self._roll(self.clock())
        out, self._ended = sorted(self._ended.items()), {}
        return out
