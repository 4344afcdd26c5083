"""The per-peer budgets (daemon/budget.py) refill on the daemon's own clock, not on wall time:
with the test's clock frozen a spent budget stays spent however long the test takes, and moving
that clock by a second gives back a second's refill.  (Before, both budgets read
time.monotonic(), so a test could not drive them and a daemon run on a simulated clock refilled
them at real speed.)"""
from __future__ import annotations

from daemon import budget as budgets
from daemon import wire
from daemon.dispatch import OSC_ERRORS_PER_S
from tests.test_daemon_units import FakeClock, _Recording


def _status(d, peer: bytes, n: int) -> list[str]:
    """``n`` status requests from one peer in one turn; the reasons of the refusals, in order."""
    items = [(wire.encode(wire.Control("status")), ("router", [peer]), d.clock()) for _ in range(n)]
    d.sent.clear()
    d.turn(d.clock(), items=items)
    return [m.reason if isinstance(m, wire.ErrorMsg) else "ok" for _, m in d.sent]


def test_control_budget_refills_on_the_daemons_clock():
    clock = FakeClock()
    d = _Recording.make(3, clock=clock)
    burst = int(budgets.BURST // budgets.CONTROL_COST)
    first = _status(d, b"peer-a", burst + 5)
    assert first[:burst] == ["ok"] * burst and first[burst:] == ["rate_limited"] * 5, first[burst - 2:]
    # the clock has not moved: still spent, whatever the wall clock did meanwhile
    assert _status(d, b"peer-a", 3) == ["rate_limited"] * 3
    # another peer has its own budget
    assert _status(d, b"peer-b", 2) == ["ok", "ok"]
    # one second of the daemon's clock gives RATE units back: RATE / CONTROL_COST requests
    clock.advance(1.0)
    per_s = int(budgets.RATE // budgets.CONTROL_COST)
    again = _status(d, b"peer-a", per_s + 3)
    assert again == ["ok"] * per_s + ["rate_limited"] * 3, (again.count("ok"), per_s)
    assert d.metrics.rejected["rate_limited"] == 5 + 3 + 3


def test_osc_error_answers_are_limited_on_the_daemons_clock():
    clock = FakeClock()
    d = _Recording.make(3, clock=clock)
    src = ("osc", ("127.0.0.9", 9000))

    def junk(n: int) -> int:
        d.sent.clear()
        d.turn(d.clock(), items=[(b"/not/lacuna\x00", src, d.clock()) for _ in range(n)])
        return sum(isinstance(m, wire.ErrorMsg) for _, m in d.sent)

    assert junk(OSC_ERRORS_PER_S + 10) == OSC_ERRORS_PER_S  # (the burst: the rest counted, not sent)
    assert junk(5) == 0  # the clock has not moved
    clock.advance(0.5)
    assert junk(OSC_ERRORS_PER_S) == OSC_ERRORS_PER_S // 2
    assert d.metrics.counters["osc_errors_unanswered"] == 10 + 5 + OSC_ERRORS_PER_S // 2
