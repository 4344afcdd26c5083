"""The daemon's model table: named models from the config, loaded, checked and warmed up.

Loading is separated from swapping so SIGHUP can load and check new files on a thread while
the main loop keeps serving with the old ones, then swap between two scheduler ticks.
"""
from __future__ import annotations

import datetime as _dt
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from daemon import positions
from daemon.config import Config, ModelSpec
from daemon.fillers import PassThroughModel
from daemon.safeopen import NotRegularFile, proc_path, regular_fd
from daemon.scheduler import CostModel, Scheduler
from lacuna.filler import Model
from lacuna.modelfile import ModelFileError, load_model


@dataclass
class Loaded:
    name: str
    model: Model
    spec: ModelSpec
    stamp: tuple[int, int] | None  # (mtime_ns, size) of the file when loaded
    loaded_at: str
    costs: dict[tuple[int, int | None], CostModel] = field(default_factory=dict)

    def info(self) -> dict[str, Any]:
        d: dict[str, Any] = {"file": self.spec.file, "builtin": self.spec.builtin, "loaded_at": self.loaded_at}
        try:
            d.update(self.model.info())
        except Exception as e:  # noqa: BLE001 - info() is cosmetic; a model bug there must not break status
            d["info_error"] = f"{type(e).__name__}: {e}"[:200]
        return {k: v for k, v in d.items() if v is not None and isinstance(v, (str, int, float, bool, list))}


def file_stamp(path: str) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_mtime_ns, st.st_size


def _load_regular(path: str) -> Model:
    """``load_model`` of a regular file only: opened without blocking and checked first (a FIFO
    or a device at the path would block the reload thread forever), then read through the
    checked descriptor (daemon/safeopen.py)."""
    try:
        with regular_fd(path) as fd:
            via = proc_path(fd)
            try:
                got: Model = load_model(via or path)
                return got
            except ModelFileError as e:
                raise ModelFileError(str(e).replace(via, path) if via else str(e)) from None
    except NotRegularFile as e:
        raise ModelFileError(f"{e}; refusing to read it") from None
    except OSError as e:
        raise ModelFileError(f"{path}: cannot read model file ({e.strerror or e})") from None


def load_one(spec: ModelSpec, budget_ms: float) -> Loaded:
    """Load and warm up one model.  Raises ModelFileError/ValueError naming the file and cause."""
    if spec.builtin == "passthrough":
        model: Model = PassThroughModel(spec.channels)
        stamp = None
    else:
        assert spec.file is not None
        stamp = file_stamp(spec.file)
        model = _load_regular(spec.file)
        if not model.causal:
            raise ModelFileError(f"{spec.file}: method {model.method!r} is not causal (it needs the future); "
                                 f"the daemon serves causal fillers only")
    tmp = Scheduler(budget_ms, 0, 1 << 30)
    C = len(model.channels)
    if C:
        try:
            tmp.warm_up(model, C)
        except Exception as e:  # noqa: BLE001 - the loop goes on
            raise ModelFileError(f"{spec.file or spec.name}: model failed its warm-up step ({type(e).__name__}: {e})") from None
    positions.warm(model, spec.name)  # FK of its skeleton compiled now, not in a stream's hello
    now = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    return Loaded(spec.name, model, spec, stamp, now, tmp.costs)


def load_all(cfg: Config, old: dict[str, Loaded] | None = None,
             progress: Callable[[str, dict[str, Any]], None] | None = None) -> tuple[dict[str, Loaded], dict[str, str]]:
    """Load every model of ``cfg``.  With ``old`` (a reload), unchanged files keep their loaded
    model and a file that fails keeps the old model; returns (table, {name: error}).

    ``progress(event, fields)`` (the daemon's log) hears ``loading`` before each model it loads and
    ``loaded`` (with the seconds taken) after: the first start after an install compiles the
    numba kernels in the warm-up, about a minute on a busy 2-core machine, cached afterwards."""
    table: dict[str, Loaded] = {}
    errors: dict[str, str] = {}
    for name, spec in cfg.models.items():
        prev = (old or {}).get(name)
        if prev is not None and prev.spec == spec and (spec.builtin or prev.stamp == file_stamp(spec.file or "")):
            table[name] = prev
            continue
        t0 = time.monotonic()
        if progress is not None:
            progress("loading", {"model": name, "file": spec.file, "builtin": spec.builtin})
        try:
            table[name] = load_one(spec, cfg.budget_ms)
            if progress is not None:
                progress("loaded", {"model": name, "seconds": round(time.monotonic() - t0, 3)})
        except (ModelFileError, ValueError, OSError, KeyError, TypeError) as e:
            errors[name] = str(e)
            if prev is not None:
                table[name] = prev
    return table, errors
