"""Counters and latency percentiles, as a status map and as Prometheus text (served by daemon/metrics_http.py).

Latency is the daemon's processing time per served frame (receipt to reply), kept in a fixed
ring of the last ``WINDOW`` values so memory stays flat however long the daemon runs.
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np

WINDOW = 20000  # latencies kept for percentiles


class Metrics:
    def __init__(self) -> None:
        self.counters: dict[str, int] = {}
        self.rejected: dict[str, int] = {}  # by reason
        self._lat = np.zeros(WINDOW)  # seconds
        self._n = 0
        self._step = np.zeros(WINDOW)
        self._ns = 0
        self.started = time.time()

    def inc(self, name: str, by: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + by

    def reject(self, reason: str) -> None:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        self.inc("rejected")

    def latency(self, seconds: float) -> None:
        self._lat[self._n % WINDOW] = seconds
        self._n += 1

    def latencies(self, seconds: float, n: int) -> None:
        """:meth:`latency` ``n`` times (a bundle's frames, all received and sent together)."""
        a, b = self._n % WINDOW, self._n % WINDOW + min(n, WINDOW)
        self._lat[a:min(b, WINDOW)] = seconds
        self._lat[: max(0, b - WINDOW)] = seconds
        self._n += n

    def step_time(self, seconds: float) -> None:
        self._step[self._ns % WINDOW] = seconds
        self._ns += 1

    @staticmethod
    def _pct(buf: np.ndarray, n: int) -> dict[str, float | int]:
        a = buf[: min(n, WINDOW)]
        if a.size == 0:
            return {"count": n}
        q = np.percentile(a, [50, 90, 99, 99.9]) * 1e3
        return {"count": n, "window": int(a.size), "p50_ms": round(float(q[0]), 4), "p90_ms": round(float(q[1]), 4),
                "p99_ms": round(float(q[2]), 4), "p999_ms": round(float(q[3]), 4),
                "max_ms": round(float(a.max() * 1e3), 4), "mean_ms": round(float(a.mean() * 1e3), 4)}

    def latency_summary(self) -> dict[str, float | int]:
        return self._pct(self._lat, self._n)

    def step_summary(self) -> dict[str, float | int]:
        return self._pct(self._step, self._ns)

    def prometheus(self, status: dict[str, Any]) -> str:
        """Prometheus text exposition format 0.0.4."""
        L: list[str] = []

        def metric(name: str, kind: str, help_: str, rows: list[tuple[str, float]]) -> None:
            L.append(f"# HELP {name} {help_}")
            L.append(f"# TYPE {name} {kind}")
            for labels, v in rows:
                L.append(f"{name}{labels} {v}")

        metric("lacuna_up", "gauge", "1 while the daemon serves", [("", 1)])
        metric("lacuna_uptime_seconds", "gauge", "seconds since start", [("", round(time.time() - self.started, 3))])
        for k in sorted(self.counters):
            metric(f"lacuna_{k}_total", "counter", f"frames/messages counted as {k}", [("", self.counters[k])])
        metric("lacuna_rejected_by_reason_total", "counter", "rejected messages by reason",
               [(f'{{reason="{_esc(r)}"}}', v) for r, v in sorted(self.rejected.items())])
        lat = self.latency_summary()
        q = [("0.5", "p50_ms"), ("0.9", "p90_ms"), ("0.99", "p99_ms"), ("0.999", "p999_ms")]
        metric("lacuna_processing_seconds", "summary", "receipt-to-reply time of served frames (recent window)",
               [(f'{{quantile="{qq}"}}', lat[k] / 1e3) for qq, k in q if k in lat] + [("_count", lat["count"])])
        loop = status.get("loop") or {}
        if loop:
            metric("lacuna_loop_stalls_total", "counter", "loop turns that woke later than asked, by how much",
                   [(f'{{over="{k}"}}', v) for k, v in loop["stalls_over"].items()])
            metric("lacuna_loop_max_stall_seconds", "gauge", "the latest wake-up so far",
                   [("", loop["max_stall_ms"] / 1e3)])
            metric("lacuna_loop_long_turns_total", "counter", "loop turns that took this long from waking to sleeping",
                   [(f'{{over="{k}"}}', v) for k, v in loop["long_turns_over"].items()])
        streams = status.get("streams", {})
        metric("lacuna_streams", "gauge", "open streams", [("", status.get("streams_total", len(streams)))])
        for key in ("frames_in", "frames_out", "dropped", "rejected", "degraded", "predicted"):
            metric(f"lacuna_stream_{key}_total", "counter", f"per-stream {key} (the most recently active streams)",
                   [(f'{{stream="{_esc(sid)}",model="{_esc(s["model"])}"}}', s[key]) for sid, s in sorted(streams.items())])
        metric("lacuna_model_loaded", "gauge", "models loaded",
               [(f'{{model="{_esc(n)}",method="{_esc(str(m.get("method")))}"}}', 1) for n, m in sorted(status.get("models", {}).items())])
        return "\n".join(L) + "\n"


def _esc(s: str) -> str:
    return s.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
