"""daemon/ratelimit.py on a fake clock: the log is limited, the count of what was held back is exact."""
from __future__ import annotations

import pytest

from daemon.ratelimit import EventLimiter


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_limiter_lets_a_burst_through_and_counts_the_rest_exactly():
    c = Clock()
    lim = EventLimiter(burst=3, window_s=5.0, clock=c)
    allowed = [lim.allow("not_msgpack") for _ in range(10)] + [lim.allow("version") for _ in range(2)]
    assert allowed == [True] * 3 + [False] * 7 + [True, True]
    assert lim.flush() == []  # the window is still running
    c.t = 5.0
    assert lim.flush() == [("not_msgpack", 7)]
    assert lim.flush() == []
    assert lim.allow("not_msgpack")  # a new window
    c.t = 20.0  # events after a quiet spell roll the window themselves; nothing is lost
    for _ in range(5):
        lim.allow("x")
    c.t = 26.0
    lim.allow("x")
    assert lim.flush() == [("x", 2)]
    assert lim.suppressed_total == 9


def test_limiter_rejects_impossible_settings():
    with pytest.raises(ValueError, match="burst"):
        EventLimiter(burst=0)
