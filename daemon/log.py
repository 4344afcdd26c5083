"""The daemon's log: one JSON object a line on stderr (``{"ts", "level", "event", ...}``)."""
from __future__ import annotations

import json
import sys
import time
from typing import Any

LEVELS = {"debug": 10, "info": 20, "warning": 30, "error": 40}


class Log:
    """JSON lines on stderr: {"ts", "level", "event", ...fields}."""

    def __init__(self, level: str = "info", stream: Any = None):
        self.level = LEVELS[level]
        self.stream = stream or sys.stderr

    def __call__(self, level: str, event: str, always: bool = False, **fields: Any) -> None:
        # lifecycle events (ready, reload_done, stopped) are logged whatever the level: tools
        # and tests wait for them
        if LEVELS[level] < self.level and not always:
            return
        rec = {"ts": round(time.time(), 6), "level": level, "event": event, **fields}
        try:
            self.stream.write(json.dumps(rec, default=str) + "\n")
            self.stream.flush()
        except (OSError, ValueError):
            pass
