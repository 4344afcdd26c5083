"""Waiting on events instead of sleeping: ``wait_until(condition, timeout)`` polls a condition
and fails the test, saying what it waited for, when the timeout passes."""
from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")

POLL_S = 0.01  # seconds between looks at the condition


def wait_until(condition: Callable[[], T], timeout: float = 10.0, what: str = "condition",
               interval: float = POLL_S) -> T:
    """Call ``condition`` until it returns something truthy and return that; AssertionError after
    ``timeout`` seconds naming ``what`` and the last value seen."""
    deadline = time.monotonic() + timeout
    last: T = condition()
    while not last:
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what} (last: {last!r})")
        time.sleep(interval)
        last = condition()
    return last
