"""`lacuna serve` configuration: TOML (tomllib), validated in one pass with errors naming the key.

Example (systemd/lacuna.toml has the annotated version)::

    [daemon]
    budget_ms = 4.0
    default_model = "walk"

    [models.walk]
    file = "/var/lib/lacuna/walk.npz"

    [models.floor]
    builtin = "passthrough"

    [zmq]
    router = "tcp://127.0.0.1:5555"
    pub = "tcp://127.0.0.1:5557"

Relative model paths are resolved against the config file's directory, so a config and its
models can move together.
"""
from __future__ import annotations

import os
import tomllib
from dataclasses import dataclass, field
from typing import Any

from daemon import security
from daemon.errors import ConfigError as ConfigError  # (re-exported: callers say config.ConfigError)

BUILTINS = ("passthrough",)
LOG_LEVELS = ("debug", "info", "warning", "error")
OVERDUE = ("drop", "serve")
PREWARM_SPIN_MS = 2.0  # after a rehearsal, poll without sleeping this long for the frame it warmed for (bench/notebook/spin-38.md)
PREWARM_MS = 0.5  # default lead of the rehearsal before a frame is due (docs/BENCHMARKS.md, "Prewarm")


@dataclass
class ModelSpec:
    name: str
    file: str | None = None  # a lacuna model file
    builtin: str | None = None  # "passthrough"
    channels: list[str] | None = None  # builtins only: their channel list


@dataclass
class Config:
    path: str | None = None
    budget_ms: float = 4.0
    idle_timeout_s: float = 30.0
    max_streams: int = 1024
    max_message_bytes: int = 65536
    max_gap_frames: int = 12
    max_batch: int = 256
    log_level: str = "info"
    busy_poll_ms: float = 0.0  # spin this long after the last message before sleeping in poll (0: never spin)
    cpu_latency_us: int | None = None  # PM QoS request held while running (daemon/pmqos.py); None: none
    realtime_priority: int | None = None  # SCHED_RR priority for the serving threads (daemon/realtime.py); None: ordinary
    overdue: str = "drop"  # a frame that cannot be answered within budget_ms of receipt: "drop" it or "serve" it late
    prewarm_ms: float = PREWARM_MS  # rehearse the last frame this long before the next is due (daemon/prewarm.py); 0: off
    prewarm_spin_ms: float = PREWARM_SPIN_MS  # then spin up to this long for that frame instead of sleeping (daemon/wait.py); 0: sleep
    default_model: str = ""
    models: dict[str, ModelSpec] = field(default_factory=dict)
    stream_models: dict[str, str] = field(default_factory=dict)
    zmq_router: str | None = "tcp://127.0.0.1:5555"
    zmq_pull: str | None = None
    zmq_sub: list[str] = field(default_factory=list)
    zmq_pub: str | None = None
    zmq_hwm: int = 1000
    osc_listen: tuple[str, int] | None = None
    osc_send: tuple[str, int] | None = None
    metrics_http: tuple[str, int] | None = None
    metrics_allow: list[str] | None = None  # source addresses/networks the metrics endpoint answers (needed off loopback)
    metrics_view: bool = False  # the metrics endpoint also serves the live view at /view/ (view/in_daemon.py)
    security: Any = None  # daemon.security.SecuritySpec, set by security.apply_config
    metrics_networks: Any = None  # metrics_allow parsed (security.apply_config)

    def summary(self) -> dict[str, Any]:
        return {"path": self.path, "budget_ms": self.budget_ms, "overdue": self.overdue, "busy_poll_ms": self.busy_poll_ms,
                "prewarm_ms": self.prewarm_ms, "prewarm_spin_ms": self.prewarm_spin_ms, "cpu_latency_us": self.cpu_latency_us, "realtime_priority": self.realtime_priority,
                "default_model": self.default_model,
                "router": self.zmq_router, "pull": self.zmq_pull, "sub": self.zmq_sub, "pub": self.zmq_pub,
                "osc_listen": _hp(self.osc_listen), "osc_send": _hp(self.osc_send),
                "metrics_http": _hp(self.metrics_http)}


def _hp(a: tuple[str, int] | None) -> str | None:
    return None if a is None else f"{a[0]}:{a[1]}"


_SCHEMA: dict[str, dict[str, tuple[type | tuple[type, ...], Any]]] = {
    # key: (type, check) ; check is (lo, hi) for numbers, a tuple of choices for strings, or None
    "daemon": {
        "budget_ms": ((int, float), (0.05, 1000.0)),
        "idle_timeout_s": ((int, float), (0.01, 86400.0)),
        "max_streams": (int, (1, 100000)),
        "max_message_bytes": (int, (64, 16 << 20)),
        "max_gap_frames": (int, (0, 100000)),
        "max_batch": (int, (1, 100000)),
        "log_level": (str, LOG_LEVELS),
        "busy_poll_ms": ((int, float), (0.0, 1000.0)),
        "prewarm_ms": ((int, float), (0.0, 100.0)),
        "prewarm_spin_ms": ((int, float), (0.0, 100.0)),
        "cpu_latency_us": (int, (0, 1_000_000)),
        "overdue": (str, OVERDUE),
        "realtime_priority": (int, (1, 99)),
        "default_model": (str, None),
    },
    "zmq": {
        "router": (str, None), "pull": (str, None), "pub": (str, None), "sub": (list, None),
        "hwm": (int, (1, 10_000_000)),
    },
    "osc": {"listen": (str, None), "send": (str, None)},
    "metrics": {"http": (str, None), "allow": (list, None), "view": (bool, None)},
}


def _check_value(where: str, key: str, v: Any, kind: Any, check: Any) -> Any:
    ok = isinstance(v, kind) and not (isinstance(v, bool) and bool not in (kind if isinstance(kind, tuple) else (kind,)))
    if not ok:
        names = {int: "an integer", float: "a number", str: "a string", list: "a list"}
        want = " or ".join(names.get(k, k.__name__) for k in (kind if isinstance(kind, tuple) else (kind,)))
        raise ConfigError(f"{where}: {key} must be {want} (got {v!r:.60})")
    if isinstance(check, tuple) and len(check) == 2 and all(isinstance(c, (int, float)) for c in check) and not isinstance(v, str):
        lo, hi = check
        if not lo <= v <= hi:
            raise ConfigError(f"{where}: {key} must be between {lo} and {hi} (got {v})")
    elif isinstance(check, tuple) and isinstance(v, str) and v not in check:
        raise ConfigError(f"{where}: {key} must be one of {list(check)} (got {v!r})")
    return v


def parse_hostport(where: str, key: str, s: str) -> tuple[str, int]:
    host, sep, port = s.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ConfigError(f"{where}: {key} must be \"host:port\" (got {s!r})")
    return host.strip("[]"), int(port)


def _zmq_endpoint(where: str, key: str, s: str) -> str:
    if not s.startswith(("tcp://", "ipc://", "inproc://")):
        raise ConfigError(f"{where}: {key} must be a ZeroMQ endpoint like tcp://127.0.0.1:5555 (got {s!r})")
    return s


def from_dict(raw: dict[str, Any], path: str | None = None) -> Config:
    """Validate a parsed TOML document.  Raises ConfigError naming the key and what arrived."""
    where = path or "<config>"
    base = os.path.dirname(os.path.abspath(path)) if path else os.getcwd()
    known = set(_SCHEMA) | {"models", "streams", "security"}
    for top in raw:
        if top not in known:
            raise ConfigError(f"{where}: unknown section [{top}] (known: {', '.join(sorted(known))})")
    cfg = Config(path=os.path.abspath(path) if path else None)
    vals: dict[str, dict[str, Any]] = {}
    for section, keys in _SCHEMA.items():
        sec = raw.get(section, {})
        if not isinstance(sec, dict):
            raise ConfigError(f"{where}: [{section}] must be a table (got {type(sec).__name__})")
        for k in sec:
            if k not in keys:
                raise ConfigError(f"{where}: unknown key {section}.{k} (known: {', '.join(sorted(keys))})")
        vals[section] = {k: _check_value(where, f"{section}.{k}", v, *keys[k]) for k, v in sec.items()}

    d = vals["daemon"]
    cfg.budget_ms = float(d.get("budget_ms", cfg.budget_ms))
    cfg.idle_timeout_s = float(d.get("idle_timeout_s", cfg.idle_timeout_s))
    cfg.busy_poll_ms = float(d.get("busy_poll_ms", cfg.busy_poll_ms))
    cfg.prewarm_ms = float(d.get("prewarm_ms", cfg.prewarm_ms))
    cfg.prewarm_spin_ms = float(d.get("prewarm_spin_ms", cfg.prewarm_spin_ms))
    for k in ("max_streams", "max_message_bytes", "max_gap_frames", "max_batch", "log_level", "cpu_latency_us", "overdue",
              "realtime_priority"):
        if k in d:
            setattr(cfg, k, d[k])
    if cfg.realtime_priority is not None and cfg.busy_poll_ms > 0:
        # a real-time thread that spins keeps ordinary work off its core, the kernel's own network
        # processing (ksoftirqd) and the capture software included: on the 2-core VM of
        # docs/BENCHMARKS.md round trips then took tens of milliseconds and most frames overran
        raise ConfigError(f"{where}: daemon.realtime_priority and daemon.busy_poll_ms > 0 cannot be used together "
                          f"(a spinning real-time thread starves the kernel's network processing on its core); "
                          f"choose one")

    models = raw.get("models", {})
    if not isinstance(models, dict) or not models:
        raise ConfigError(f"{where}: [models] must name at least one model, e.g. [models.walk] file = \"walk.npz\"")
    for name, spec in models.items():
        key = f"models.{name}"
        if not isinstance(spec, dict):
            raise ConfigError(f"{where}: [{key}] must be a table with file = \"...\" or builtin = \"...\"")
        extra = set(spec) - {"file", "builtin", "channels"}
        if extra:
            raise ConfigError(f"{where}: unknown key {key}.{sorted(extra)[0]} (known: builtin, channels, file)")
        if ("file" in spec) == ("builtin" in spec):
            raise ConfigError(f"{where}: [{key}] needs exactly one of file = \"...\" or builtin = \"...\"")
        if "file" in spec:
            f = _check_value(where, f"{key}.file", spec["file"], str, None)
            if "channels" in spec:
                raise ConfigError(f"{where}: {key}.channels is only for builtin models (a model file has its own)")
            cfg.models[name] = ModelSpec(name, file=f if os.path.isabs(f) else os.path.join(base, f))
        else:
            b = _check_value(where, f"{key}.builtin", spec["builtin"], str, BUILTINS)
            ch = spec.get("channels")
            if ch is not None and (not isinstance(ch, list) or not ch or not all(isinstance(c, str) and c for c in ch)
                                   or len(set(ch)) != len(ch)):
                raise ConfigError(f"{where}: {key}.channels must be a list of distinct channel names (got {ch!r:.60})")
            cfg.models[name] = ModelSpec(name, builtin=b, channels=ch)
    # unless told otherwise, streams get the model named "default" (the recommended filler,
    # `lacuna train default`) where the config has one, else the first model listed
    cfg.default_model = d.get("default_model") or ("default" if "default" in cfg.models else next(iter(cfg.models)))
    if cfg.default_model not in cfg.models:
        raise ConfigError(f"{where}: daemon.default_model {cfg.default_model!r} is not under [models] "
                          f"(have: {', '.join(cfg.models)})")

    streams = raw.get("streams", {})
    if not isinstance(streams, dict):
        raise ConfigError(f"{where}: [streams] must be a table of [streams.<id>] model = \"...\"")
    for sid, spec in streams.items():
        if not isinstance(spec, dict) or set(spec) != {"model"} or not isinstance(spec["model"], str):
            raise ConfigError(f"{where}: [streams.{sid}] must hold exactly model = \"<name>\" (got {spec!r:.60})")
        if spec["model"] not in cfg.models:
            raise ConfigError(f"{where}: streams.{sid}.model {spec['model']!r} is not under [models]")
        cfg.stream_models[sid] = spec["model"]

    z = vals["zmq"]
    if "router" in z:
        cfg.zmq_router = _zmq_endpoint(where, "zmq.router", z["router"]) if z["router"] else None
    if z.get("pull"):
        cfg.zmq_pull = _zmq_endpoint(where, "zmq.pull", z["pull"])
    if z.get("pub"):
        cfg.zmq_pub = _zmq_endpoint(where, "zmq.pub", z["pub"])
    for i, s in enumerate(z.get("sub", [])):
        if not isinstance(s, str):
            raise ConfigError(f"{where}: zmq.sub[{i}] must be a string endpoint (got {s!r:.60})")
        cfg.zmq_sub.append(_zmq_endpoint(where, f"zmq.sub[{i}]", s))
    cfg.zmq_hwm = z.get("hwm", cfg.zmq_hwm)
    o = vals["osc"]
    if o.get("listen"):
        cfg.osc_listen = parse_hostport(where, "osc.listen", o["listen"])
    if o.get("send"):
        cfg.osc_send = parse_hostport(where, "osc.send", o["send"])
    if o.get("send") and not o.get("listen"):
        raise ConfigError(f"{where}: osc.send is set but osc.listen is not (OSC output answers OSC input)")
    m = vals["metrics"]
    if m.get("http"):
        cfg.metrics_http = parse_hostport(where, "metrics.http", m["http"])
    if "allow" in m:
        if not all(isinstance(a, str) for a in m["allow"]):
            raise ConfigError(f"{where}: metrics.allow must be a list of addresses or networks (got {m['allow']!r:.60})")
        cfg.metrics_allow = list(m["allow"])
    cfg.metrics_view = bool(m.get("view"))
    if cfg.metrics_view and not (cfg.metrics_http and cfg.zmq_pub):
        raise ConfigError(f"{where}: metrics.view needs metrics.http (where the page is served) and zmq.pub (what it shows)")
    if not (cfg.zmq_router or cfg.zmq_pull or cfg.zmq_sub or cfg.osc_listen):
        raise ConfigError(f"{where}: no input configured (set zmq.router, zmq.pull, zmq.sub or osc.listen)")
    if (cfg.zmq_pull or cfg.zmq_sub) and not cfg.zmq_pub:
        raise ConfigError(f"{where}: zmq.pull/zmq.sub need zmq.pub for the filled frames to go somewhere")
    security.apply_config(cfg, raw.get("security"), where, base)  # refuses non-loopback binds without CURVE
    return cfg


def load(path: str) -> Config:
    """Read and validate a TOML config file."""
    from daemon.safeopen import read_regular  # (a FIFO or device at the path must not block the reload)

    try:
        raw = tomllib.loads(read_regular(path, 16 << 20).decode("utf-8"))
    except OSError as e:
        raise ConfigError(f"{path}: cannot read config ({e.strerror or e})") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML ({e})") from None
    except UnicodeDecodeError as e:  # e.g. saved as UTF-16 by an editor: TOML is UTF-8
        raise ConfigError(f"{path}: not UTF-8 text (byte {e.start}: {e.reason})") from None
    return from_dict(raw, path)
