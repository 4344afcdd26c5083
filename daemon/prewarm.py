"""Keep the serving path warm for the next frame (``[daemon] prewarm_ms``).

On the 2-core virtual machine of docs/BENCHMARKS.md a frame handled 8 ms after the previous one
costs 3-4 times what it costs right after one, and not because the thread slept: the same wait
spent spinning costs as much.  What the CPU cached of the daemon's code and data (the
interpreter's, numpy's, the model's tables) is gone after a few milliseconds of other work on the
machine; after 1 ms most of it is still there.  A capture system sends on a fixed clock, so the
daemon knows when the next frame is due.  Shortly before that it rehearses: the last frame it
served goes once more through decoding, the scheduler's plan, the model's step, the fill message
and its encoding, on a shadow of the stream (its own filter state, one per model, answering
nobody).  The real frame then finds that path warm.

Nothing a stream sees changes: the shadow has its own state, its step is not counted in the
scheduler's cost estimates, and nothing is sent.  A rehearsal runs only when no frame is waiting,
at most once per frame served, when the stream's period is regular and between
``MIN_PERIOD_S`` and ``MAX_PERIOD_S``, and when the model's step is estimated to fit in
``MAX_STEP_S``.  It costs one more step per period (a few percent of a core for one HLM stream
at 120 Hz).  Frames served as a bundle's block (daemon/tickblock.py) plan no rehearsal.  A frame
that lands while a rehearsal runs waits for it; the loop then stamps it with the rehearsal's
start (daemon/wait.py), so its ``proc_us`` and the latency in ``status`` show that wait.
"""
from __future__ import annotations

import time
from typing import Any

from daemon import wire
from daemon.encode import fill_message, model_inputs
from daemon.scheduler import Scheduler, levels_of
from daemon.session import Pending, Session
from lacuna.filler import FillerState, Model

MAX_PERIOD_S = 0.1    # streams slower than 10 Hz are not rehearsed for (their frames are few)
MIN_PERIOD_S = 0.003  # nor frames closer than this: 1-2 ms after a frame the path is still about as
                      # warm as right after it (bench/cold_decay.py), and a daemon so busy needs no
                      # more work (at 4x overload the turns came 2 ms apart)
MIN_GAP_S = 0.0015    # turns closer than this are one burst, not the stream's period
MAX_STEP_S = 0.001    # a model whose step is estimated above this is not rehearsed (a rehearsal
                      # running when the frame lands delays it by what is left of it)
GAPS = 8              # the period is the median of the last GAPS gaps between frames


class Prewarm:
    def __init__(self, lead_ms: float):
        self.lead_s = lead_ms / 1000.0
        self.due: float | None = None           # perf_counter at which to rehearse, or None
        self._last: tuple[Session, wire.Frame] | None = None
        self._arrived: float | None = None       # receipt of the last frame served
        self._gaps: list[float] = []
        self._shadows: dict[int, tuple[Model, FillerState]] = {}  # id(model) -> (model, shadow state)
        self.count = 0
        self.errors = 0
        self.last_error = ""
        self.spent_s = 0.0
        self.spins = 0          # waits spun after a rehearsal (daemon/wait.py, prewarm_spin_ms)
        self.spin_caught = 0    # of them, those a message ended (the rest ran out and slept in poll)
        self.spin_s = 0.0       # time spent spinning

    @property
    def on(self) -> bool:
        return self.lead_s > 0.0

    def period(self) -> float | None:
        g = sorted(self._gaps)
        return g[len(g) // 2] if len(g) >= 3 else None

    def served(self, s: Session, frame: wire.Frame, arrived: float, sched: Scheduler) -> None:
        """A turn served ``frame`` of ``s`` (read at ``arrived``): plan the next rehearsal."""
        if self._arrived is not None:
            gap = arrived - self._arrived
            if MIN_GAP_S <= gap:
                self._gaps.append(gap)
                del self._gaps[:-GAPS]
        self._arrived = arrived
        self._last = (s, frame)
        per = self.period()
        self.due = None
        if per is None or not MIN_PERIOD_S <= per <= MAX_PERIOD_S:
            return
        cm = sched.cost(s.model, levels_of(s.model)[0])
        step = cm.estimate(1) if cm.seen else 0.0
        if step > MAX_STEP_S:
            return
        # rehearse lead_s (and the step's own time) before the frame is due
        self.due = arrived + per - self.lead_s - step

    def forget_models(self) -> None:
        """Models were swapped (a reload): their shadows go with them."""
        self._shadows.clear()
        self._last = None
        self.due = None

    def rehearse(self, sessions: dict[str, Session], sched: Scheduler, encode: Any) -> None:
        """One rehearsal of the last frame served, if its stream is still the one it was."""
        self.due = None
        last, self._last = self._last, None
        if last is None:
            return
        s, f = last
        if sessions.get(s.sid) is not s:  # reset, expired or re-handshaken since
            return
        t0 = time.perf_counter()
        try:
            model = s.model
            got = self._shadows.get(id(model))
            if got is None or got[0] is not model:
                got = self._shadows[id(model)] = (model, model.stream())
            g = wire.decode(encode(f))
            assert isinstance(g, wire.Frame)
            sh = Session(s.sid, s.model_name, model, s.mapping, got[1], last_seq=s.last_seq,
                         pending=Pending(g, ("router", []), t0))
            sched.plan(model, [sh], t0)  # (pure: reads the costs)
            mf, mo = model_inputs([sh], s.mapping.n_model)
            fill = model.step_batch([sh.state], mf, mo)[0]
            encode(fill_message(sh, fill, "ok", time.perf_counter()))
            self.count += 1
        except Exception as e:  # noqa: BLE001 - a rehearsal must never cost a frame: count it and go on
            self.errors += 1
            self.last_error = f"{type(e).__name__}: {e}"[:300]
            self._shadows.pop(id(s.model), None)
        finally:
            self.spent_s += time.perf_counter() - t0

    def spun(self, caught: bool, seconds: float) -> None:
        """A wait after a rehearsal spun ``seconds`` for its frame (daemon/wait.py, ``prewarm_spin_ms``);
        ``caught``: a message ended it (else it ran out and the loop slept in poll)."""
        self.spins += 1
        self.spin_caught += caught
        self.spin_s += seconds

    def info(self) -> dict[str, Any]:
        per = self.period()
        return {"lead_ms": round(self.lead_s * 1000, 3), "rehearsals": self.count, "errors": self.errors,
                "last_error": self.last_error, "period_ms": None if per is None else round(per * 1000, 3),
                "spent_ms": round(self.spent_s * 1000, 3), "spins": self.spins, "spin_caught": self.spin_caught,
                "spin_ms": round(self.spin_s * 1000, 3)}
