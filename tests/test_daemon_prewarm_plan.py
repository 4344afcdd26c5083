"""daemon.prewarm's plan: the rehearsal is to have *ended* lead_s before the next frame is due, so
it starts lead_s + the larger of the step's estimate and the rehearsal's own time (the median of
the last rehearsals) before it; a frame landing while a rehearsal still runs waits for it
(bench/notebook/hlm9.md)."""
from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest

from daemon import prewarm, wire
from daemon.fillers import PassThroughModel
from daemon.scheduler import Scheduler

PERIOD = 1 / 120


def _plan(took: list[float]) -> float | None:
    p = prewarm.Prewarm(0.5)
    p._took = list(took)
    s = SimpleNamespace(model=PassThroughModel(["a", "b"]))
    sched = Scheduler(4.0, 0, 1 << 30)
    t0 = time.perf_counter()
    for k in range(5):
        p.served(s, wire.Frame("x", k, 0.0, np.zeros(2)), t0 + k * PERIOD, sched)  # type: ignore[arg-type]
    assert p.due is not None
    return p.due - (t0 + 5 * PERIOD)   # the plan against the next frame's due time


def test_the_rehearsal_starts_its_own_time_before_the_lead():
    assert _plan([]) == pytest.approx(-0.0005, abs=1e-9)                        # nothing rehearsed yet: the step's estimate (none)
    assert _plan([0.0003, 0.0002, 0.0004]) == pytest.approx(-0.0008, abs=1e-9)  # the median rehearsal, 300 us
    assert _plan([0.05] * 3) == pytest.approx(-0.0005 - prewarm.MAX_STEP_S, abs=1e-9)  # capped


def test_a_rehearsal_records_its_time_and_a_reload_forgets_it():
    p = prewarm.Prewarm(0.5)
    p._took = [0.001] * 20
    p.forget_models()
    assert p._took == []
