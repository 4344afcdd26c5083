"""Write a daemon config (TOML) from a dict: the one writer the harness, the tests and the benches share.

``cfg`` is ``{section: {key: value}}``; a section name may be dotted (``"models.walk"``).  Values
are bools, numbers, strings or lists of them.  :func:`loopback_config` builds the usual test and
bench config on fixed free loopback ports (so a restarted daemon comes back on the same endpoints).
"""
from __future__ import annotations

import os
import socket
from pathlib import Path
from typing import Any

Config = dict[str, dict[str, Any]]


def free_port(kind: int = socket.SOCK_STREAM, host: str = "127.0.0.1") -> int:
    """A port free right now on ``host`` (the kernel picks it); ``kind`` SOCK_DGRAM for UDP."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind((host, 0))
        port: int = s.getsockname()[1]
        return port


def toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def config_text(cfg: Config, extra: str = "") -> str:
    lines: list[str] = []
    for section, keys in cfg.items():
        lines.append(f"[{section}]")
        lines += [f"{k} = {toml_value(v)}" for k, v in keys.items()]
        lines.append("")
    return "\n".join(lines) + ("\n" + extra if extra else "")


def write_config(path: str | os.PathLike[str], cfg: Config, extra: str = "") -> str:
    """Write ``cfg`` (and ``extra``, raw TOML appended) to ``path``; returns the path."""
    Path(path).write_text(config_text(cfg, extra))
    return os.fspath(path)


def loopback_config(path: str | os.PathLike[str], models: dict[str, dict[str, Any]], *, router: str | None = None,
                    pull: bool = False, pub: bool = True, osc: bool = False, daemon: dict[str, Any] | None = None,
                    extra: str = "") -> dict[str, Any]:
    """Write a config on fixed free loopback ports; returns the endpoints it names
    (``router``, ``pub``, ``pull``: ZeroMQ endpoints; ``osc``: (host, port))."""
    ep: dict[str, Any] = {"router": router or f"tcp://127.0.0.1:{free_port()}"}
    # (a generous budget: with overdue = "drop", the default, a frame a stall of the test machine
    # holds past the budget is answered `overdue`, and these configs are about other things)
    cfg: Config = {"daemon": {"budget_ms": 250.0, "idle_timeout_s": 3600, **(daemon or {})}}
    for name, spec in models.items():
        cfg[f"models.{name}"] = dict(spec)
    z: dict[str, Any] = {"router": ep["router"]}
    if pull:
        ep["pull"] = z["pull"] = f"tcp://127.0.0.1:{free_port()}"
    if pub or pull:
        ep["pub"] = z["pub"] = f"tcp://127.0.0.1:{free_port()}"
    cfg["zmq"] = z
    if osc:
        ep["osc"] = ("127.0.0.1", free_port(socket.SOCK_DGRAM))
        cfg["osc"] = {"listen": f"127.0.0.1:{ep['osc'][1]}"}
    write_config(path, cfg, extra)
    return ep
