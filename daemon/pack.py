"""Wire messages -> bytes (msgpack): :func:`encode` is :func:`daemon.decode.decode`'s inverse (fixed key
order, so the same message always gives the same bytes)."""
from __future__ import annotations

from typing import Any

import msgpack
import numpy as np

from daemon.schema import (
    F32,
    SCHEMA_VERSION,
    Bundle,
    Control,
    ControlReply,
    Drop,
    ErrorMsg,
    FillMsg,
    Frame,
    Hello,
    HelloAck,
    Message,
    Replies,
    WireError,
)

# ---- encode ----------------------------------------------------------------------------------
_F32_NATIVE = np.dtype(np.float32) if np.dtype(np.float32) == F32 else F32  # the dtype object numpy hands out
_BOOL = np.dtype(np.bool_)


def _b32(a: np.ndarray) -> bytes:
    # (tobytes writes C order whatever the strides; the dtype is compared by identity, the
    # cheap test that holds for every array the daemon builds, the full conversion otherwise)
    if type(a) is np.ndarray and a.dtype is _F32_NATIVE:
        return a.tobytes()  # the daemon's own fills arrive like this: no conversion
    return np.ascontiguousarray(a, dtype=F32).tobytes()


def _bmask(a: np.ndarray) -> bytes:
    if type(a) is np.ndarray and a.dtype is _BOOL:
        return a.tobytes()  # bool is one 0/1 byte each
    return np.ascontiguousarray(a, dtype=bool).astype(np.uint8).tobytes()


def fill_map(msg: FillMsg) -> dict[str, Any]:
    """A fill's msgpack map (the daemon's hot path: no dispatch on the type)."""
    d: dict[str, Any] = {"v": 1, "type": "fill", "stream": msg.stream, "seq": msg.seq, "t": msg.t,
                         "angles": _b32(msg.angles), "filled": _bmask(msg.filled), "std": _b32(msg.std),
                         "status": msg.status, "model": msg.model, "proc_us": int(msg.proc_us)}
    if msg.style is not None:
        d["style"] = _b32(msg.style)
    if msg.phase is not None:
        d["phase"] = float(msg.phase)
    if msg.gap:
        d["gap"] = int(msg.gap)
    if msg.positions is not None:
        d["positions"] = _b32(msg.positions)
    return d


def to_map(msg: Message) -> dict[str, Any]:
    """Message object -> the msgpack map (fixed key order)."""
    if type(msg) is FillMsg:  # the daemon's hot path: checked first
        return fill_map(msg)
    if isinstance(msg, Frame):
        d = {"v": 1, "type": "frame", "stream": msg.stream, "seq": msg.seq, "t": msg.t,
             "angles": _b32(msg.angles)}
        if msg.observed is not None:
            d["observed"] = _bmask(msg.observed)
        return d
    if isinstance(msg, Hello):
        d = {"v": 1, "type": "hello", "stream": msg.stream, "channels": list(msg.channels)}
        if msg.model:
            d["model"] = msg.model
        if msg.claim:
            d["claim"] = msg.claim
        if msg.positions:
            d["positions"] = True
        return d
    if isinstance(msg, HelloAck):
        d = {"v": 1, "type": "hello-ack", "stream": msg.stream, "model": msg.model,
             "channels": list(msg.channels), "passthrough": list(msg.passthrough), "missing": list(msg.missing)}
        if msg.joints is not None:
            d["joints"], d["parents"] = list(msg.joints), [int(p) for p in msg.parents or ()]
        return d
    if isinstance(msg, Drop):
        return {"v": 1, "type": "drop", "stream": msg.stream, "seq": msg.seq, "reason": msg.reason}
    if isinstance(msg, Control):
        d = {"v": 1, "type": "control", "cmd": msg.cmd}
        if msg.stream:
            d["stream"] = msg.stream
        if msg.limit is not None:
            d["limit"] = msg.limit
        return d
    if isinstance(msg, ControlReply):
        d = {"v": 1, "type": "control-reply", "cmd": msg.cmd, "ok": msg.ok, "result": msg.result}
        if msg.error is not None:
            d["error"] = msg.error
        return d
    if isinstance(msg, ErrorMsg):
        d = {"v": 1, "type": "error", "reason": msg.reason, "detail": msg.detail}
        if msg.stream is not None:
            d["stream"] = msg.stream
        if msg.seq is not None:
            d["seq"] = msg.seq
        return d
    if isinstance(msg, Bundle):
        return {"v": 1, "type": "frames", "frames": [_bundled(to_map(f)) for f in msg.items]}  # type: ignore[arg-type]
    if isinstance(msg, Replies):
        return {"v": 1, "type": "replies", "replies": [to_map(r) for r in msg.items]}
    raise TypeError(f"not a wire message: {type(msg).__name__}")


def _bundled(d: dict[str, Any]) -> dict[str, Any]:
    if d.get("type") != "frame":
        raise TypeError(f"a bundle carries frames only (got {d.get('type')})")
    del d["v"], d["type"]  # implied by the bundle
    return d


def encode(msg: Message) -> bytes:
    """Message object -> bytes (msgpack, bin type for byte strings, floats as float64)."""
    out: bytes = msgpack.packb(to_map(msg), use_bin_type=True)
    return out


_PACK = msgpack.Packer(use_bin_type=True)
_REPLIES_HEAD: bytes = _PACK.pack_map_header(3) + _PACK.pack("v") + _PACK.pack(SCHEMA_VERSION) + \
    _PACK.pack("type") + _PACK.pack("replies") + _PACK.pack("replies")


def join_replies(bodies: list[bytes]) -> bytes:
    """Encoded answers (each ``encode(msg)``) -> one ``replies`` message, without decoding them:
    a msgpack array is its header followed by its elements' bytes."""
    head: bytes = _PACK.pack_array_header(len(bodies))
    return _REPLIES_HEAD + head + b"".join(bodies)


def replies_of(maps: list[dict[str, Any]], pack: Any = None) -> bytes:
    """Answer maps (each ``to_map(msg)``) -> one ``replies`` message in one msgpack pass; the
    same bytes as ``join_replies([encode(m) for m in msgs])`` (a msgpack array is its header
    followed by its elements' bytes, and pack(list) writes exactly that)."""
    body: bytes = (pack or _PACK.pack)(maps)
    return _REPLIES_HEAD + body


def error_for(e: WireError) -> ErrorMsg:
    return ErrorMsg(e.reason, e.detail, e.stream, e.seq)
