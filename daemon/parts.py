"""What the parts of the daemon (daemon/dispatch.py, tick.py, control.py, reload.py, wait.py) share: the
attributes :class:`daemon.loop.Daemon` sets up and the few methods one part calls on another,
declared once so that each part is type-checked on its own.  Nothing here runs."""
from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from daemon import budget as budgets
    from daemon import config as config_mod
    from daemon import wire
    from daemon.layout import Layouts
    from daemon.log import Log
    from daemon.metrics import Metrics
    from daemon.metrics_http import MetricsHTTP
    from daemon.models import Loaded
    from daemon.notify import Notifier
    from daemon.pmqos import CpuLatency
    from daemon.prewarm import Prewarm
    from daemon.realtime import Realtime
    from daemon.reloader import Reloader
    from daemon.scheduler import Scheduler
    from daemon.session import Origin, Pending, Session
    from daemon.sessions import SessionTable
    from daemon.stalls import Stalls
    from daemon.transport import Transports

    Answers = list[tuple[Origin, wire.Message]]
    # (session, its last answered seq before the burst, the served frame's Pending,
    #  [(unpacked map, origin, arrived) or None where the served frame came, ...])
    SetAside = tuple[Session, int | None, Pending, list[Any]]


class Parts:
    if TYPE_CHECKING:
        cfg: config_mod.Config
        log: Log
        clock: Callable[[], float]
        metrics: Metrics
        notify: Notifier
        qos: CpuLatency
        rt: Realtime
        models: dict[str, Loaded]
        sched: Scheduler
        sessions: SessionTable
        net: Transports | None
        http: MetricsHTTP | None
        prewarm: Prewarm
        stalls: Stalls
        budget: budgets.Budget
        osc_err_budget: budgets.Budget
        reloader: Reloader | None
        started: float
        last_reload: dict[str, Any]
        flag_stop: bool
        flag_reload: bool
        _drop_overdue: bool
        _out: Answers
        _conflated: Answers
        _superseded: list[SetAside]
        _rej_window: float
        _rej_logged: int
        _rej_suppressed: int
        _osc_in: int
        _osc_errs: list[tuple[str, str]] | None
        layouts: Layouts
        _reload_args: tuple[str | None, dict[str, Loaded]]
        _switch: float
        _last_rx: float

        # (one part calls these on another)
        def _send(self, origin: Origin, msg: wire.Message, publish: bool = False) -> None: ...
        def _deliver(self, answers: Answers) -> None: ...
        def _refuse(self, origin: Origin | None, reason: str, detail: str, sid: str | None,
                    seq: int | None) -> None: ...
        def _reject(self, origin: Origin | None, reason: str, detail: str, sid: str | None,
                    seq: int | None) -> None: ...
        def _rate_limited(self, origin: Origin, m: dict[str, Any] | None = None) -> None: ...
        def _serve(self) -> None: ...
        def _answer(self, results: list[Any], t0: float) -> None: ...
        def _send_fills(self, origin: Origin, maps: list[dict[str, Any]]) -> None: ...
        def _send_held(self, answers: int | None = None, hold_on: bool = True) -> None: ...
        def _control(self, msg: wire.Control, origin: Origin) -> None: ...
        def _start_reload(self, origin: Origin | None) -> None: ...
        def _install(self, table: dict[str, Loaded]) -> None: ...
        def _request_cpu_latency(self) -> None: ...
        def _request_realtime(self) -> None: ...
        def _status_line(self) -> str: ...
        def status(self, limit: int = ..., stream: str | None = None) -> dict[str, Any]: ...
