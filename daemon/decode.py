"""Bytes -> wire messages (schema in daemon/schema.py, the rules in docs/PROTOCOL.md).

``decode(data)`` either returns one of the message dataclasses or raises :class:`WireError`
whose ``reason`` is a short stable code (``not_msgpack``, ``too_large``, ``version``,
``missing_field``, ...) that the daemon counts per reason; it never raises anything else,
whatever bytes arrive.  The daemon's hot path reads a bundle's frames as arrays at once
(:func:`frame_block`, in daemon/block.py), the rest message by message.
"""
from __future__ import annotations

import math
import sys
from collections.abc import Callable
from itertools import compress
from typing import Any

import msgpack
import numpy as np

from daemon.block import BlockBundle, no_inf, read_block
from daemon.schema import (
    CONTROL_COMMANDS,
    F32,
    MAX_BUNDLE,
    MAX_CHANNELS,
    MAX_CLAIM,
    MAX_MESSAGE_BYTES,
    MAX_NAME,
    MAX_SEQ,
    MAX_STREAM_ID,
    SCHEMA_VERSION,
    STATUSES,
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

Map = dict[str, Any]  # an unpacked msgpack map


# ---- decode ----------------------------------------------------------------------------------
def _get(m: Map, key: str, kind: type | tuple[type, ...], what: str, optional: bool = False) -> Any:
    if key not in m or (optional and m[key] is None):
        if optional:
            return None
        raise WireError("missing_field", f"{what} needs field {key!r} (got keys {sorted(map(str, m))[:12]})",
                        _sid(m), _seq(m))
    v = m[key]
    # bool is an int in Python; a bool where a number belongs is a client bug, say so
    if isinstance(v, bool) and bool not in (kind if isinstance(kind, tuple) else (kind,)):
        raise WireError("bad_type", f"{what} field {key!r} must be {_kname(kind)} (got bool)", _sid(m), _seq(m))
    if not isinstance(v, kind):
        raise WireError("bad_type", f"{what} field {key!r} must be {_kname(kind)} (got {type(v).__name__})",
                        _sid(m), _seq(m))
    return v


def _kname(kind: type | tuple[type, ...]) -> str:
    names = {int: "int", float: "float", str: "str", bytes: "bytes", list: "array", dict: "map", bool: "bool"}
    ks = kind if isinstance(kind, tuple) else (kind,)
    return " or ".join(names.get(k, k.__name__) for k in ks)


def _sid(m: Map) -> str | None:
    s = m.get("stream")
    return s if isinstance(s, str) and len(s) <= MAX_STREAM_ID else None


def _seq(m: Map) -> int | None:
    s = m.get("seq")
    return s if isinstance(s, int) and not isinstance(s, bool) and 0 <= s <= MAX_SEQ else None


def _stream_id(m: Map, what: str) -> str:
    s: str = _get(m, "stream", str, what)
    if not 0 < len(s) <= MAX_STREAM_ID:
        raise WireError("bad_stream", f"stream id must be 1..{MAX_STREAM_ID} characters (got {len(s)})")
    if not s.isprintable():
        raise WireError("bad_stream", f"stream id must be printable (got {s[:40]!r})")
    return s


def _names(v: Any, key: str, what: str, sid: str | None) -> list[str]:
    if not isinstance(v, list):
        raise WireError("bad_type", f"{what} field {key!r} must be an array of strings (got {type(v).__name__})", sid)
    if not 0 < len(v) <= MAX_CHANNELS:
        raise WireError("bad_length", f"{what} field {key!r} must list 1..{MAX_CHANNELS} names (got {len(v)})", sid)
    # (checked at C speed first: a 4096-name hello is the costliest request there is)
    if set(map(type, v)) != {str} or not 0 < min(map(len, v)) <= max(map(len, v)) <= MAX_NAME:
        for i, c in enumerate(v):
            if not isinstance(c, str) or not 0 < len(c) <= MAX_NAME:
                raise WireError("bad_type", f"{what} {key}[{i}] must be a non-empty string (got {c!r:.40})", sid)
    if len(set(v)) != len(v):  # (linear: list.count per name made a 4096-name hello cost 10-20 ms)
        seen: set[str] = set()
        dups: set[str] = set()
        for c in v:
            (dups if c in seen else seen).add(c)
        dup = sorted(dups)[:5]
        raise WireError("bad_channels", f"{what} channel names repeat: {dup}", sid)
    return list(v)


def _f32(m: Map, key: str, what: str, n: int | None, optional: bool = False) -> np.ndarray | None:
    b = _get(m, key, bytes, what, optional)
    if b is None:
        return None
    if len(b) % 4 or (n is not None and len(b) != 4 * n) or len(b) > 4 * MAX_CHANNELS:
        want = f"{4 * n}" if n is not None else f"a multiple of 4, at most {4 * MAX_CHANNELS}"
        raise WireError("bad_length", f"{what} field {key!r} must be {want} bytes of float32 (got {len(b)})",
                        _sid(m), _seq(m))
    return np.frombuffer(b, dtype=F32)


def _mask(m: Map, key: str, what: str, n: int, optional: bool = False) -> np.ndarray | None:
    b = _get(m, key, bytes, what, optional)
    if b is None:
        return None
    if len(b) != n:
        raise WireError("bad_length", f"{what} field {key!r} must be {n} bytes, one per channel (got {len(b)})",
                        _sid(m), _seq(m))
    a = np.frombuffer(b, dtype=np.uint8)
    if a.max(initial=0) > 1:
        raise WireError("bad_mask", f"{what} field {key!r} bytes must be 0 or 1 (got {int(a.max())})", _sid(m), _seq(m))
    return a.astype(bool)


def _number(m: Map, key: str, what: str) -> float:
    v = _get(m, key, (int, float), what)
    v = float(v)
    if not math.isfinite(v):
        raise WireError("bad_timestamp", f"{what} field {key!r} must be finite (got {v})", _sid(m), _seq(m))
    return v


_ADD = np.add.reduce
_LITTLE = sys.byteorder == "little" and np.dtype(F32).byteorder in ("<", "=")


def well_formed(m: Map) -> tuple[str, int, float, np.ndarray, np.ndarray | None] | None:
    """(stream, seq, t, angles, observed) of a common, well-formed frame map (the daemon's hot
    path, and daemon/aside.py's set-aside frames), else None: anything unusual goes through the
    checked path, which names what is wrong."""
    sid, seq, t, b, ob = m.get("stream"), m.get("seq"), m.get("t"), m.get("angles"), m.get("observed")
    if (type(sid) is str and 0 < len(sid) <= MAX_STREAM_ID and type(seq) is int and 0 <= seq <= MAX_SEQ
            and type(t) is float and math.isfinite(t) and type(b) is bytes and 0 < len(b) <= 4 * MAX_CHANNELS
            and not len(b) % 4 and sid.isprintable()):
        angles = np.frombuffer(b, dtype=F32)
        if ob is None:
            if no_inf(b) or not np.isinf(angles).any():
                return sid, seq, t, angles, None
        # a mask of one 0/1 byte per channel (translate deletes those bytes: nothing may be left)
        elif type(ob) is bytes and 4 * len(ob) == len(b) and not ob.translate(None, b"\x00\x01"):
            # the double sum of the observed values is finite exactly when all of them are (float32
            # values cannot overflow it; NaN and +-inf propagate), summed by CPython alone: after the
            # live wait between frames numpy's reduction with where= cost 62 us at p50, this 26
            # (bench/finite_cold.py); the wire's little-endian float32 is the native 'f' here
            observed = np.frombuffer(ob, dtype=np.bool_)
            if math.isfinite(sum(compress(memoryview(b).cast("f"), ob)) if _LITTLE
                             else _ADD(angles, where=observed, dtype=np.float64)):
                return sid, seq, t, angles, observed
    return None


def _decode_frame(m: Map) -> Frame:
    got = well_formed(m)
    return Frame(*got) if got is not None else _decode_frame_checked(m)


def _decode_frame_checked(m: Map) -> Frame:
    sid = _stream_id(m, "frame")
    seq = _get(m, "seq", int, "frame")
    if not 0 <= seq <= MAX_SEQ:
        raise WireError("bad_seq", f"frame seq must be in 0..2**63-1 (got {seq})", sid)
    t = _number(m, "t", "frame")
    angles = _f32(m, "angles", "frame", None)
    assert angles is not None
    if angles.size == 0:
        raise WireError("bad_length", "frame field 'angles' is empty", sid, seq)
    observed = _mask(m, "observed", "frame", angles.size, optional=True)
    finite = np.isfinite(angles)
    if observed is None:
        if np.isinf(angles).any():
            idx = np.flatnonzero(np.isinf(angles))[:5].tolist()
            raise WireError("non_finite", f"frame angles hold infinity at channels {idx} (NaN means missing)", sid, seq)
    elif (observed & ~finite).any():
        idx = np.flatnonzero(observed & ~finite)[:5].tolist()
        raise WireError("non_finite", f"frame marks channels {idx} observed but their values are NaN/inf", sid, seq)
    return Frame(sid, seq, t, angles, observed)


def _decode_hello(m: Map) -> Hello:
    sid = _stream_id(m, "hello")
    channels = _names(m.get("channels"), "channels", "hello", sid) if "channels" in m else None
    if channels is None:
        raise WireError("missing_field", "hello needs field 'channels'", sid)
    model = _get(m, "model", str, "hello", optional=True)
    claim = _get(m, "claim", str, "hello", optional=True)
    if claim is not None and not 0 < len(claim) <= MAX_CLAIM:
        raise WireError("bad_length", f"hello field 'claim' must be 1..{MAX_CLAIM} characters (got {len(claim)})", sid)
    positions = _get(m, "positions", bool, "hello", optional=True)
    return Hello(sid, channels, model or None, claim, bool(positions))


def _decode_control(m: Map) -> Control:
    cmd = _get(m, "cmd", str, "control")
    if cmd not in CONTROL_COMMANDS:
        raise WireError("unknown_command", f"control cmd must be one of {list(CONTROL_COMMANDS)} (got {cmd[:40]!r})")
    stream = _get(m, "stream", str, "control", optional=True)
    if cmd in ("reset", "release") and not stream:
        raise WireError("missing_field", f"control {cmd} needs field 'stream'")
    limit = _get(m, "limit", int, "control", optional=True)
    if limit is not None and not 0 <= limit <= 100000:
        raise WireError("bad_length", f"control field 'limit' must be 0..100000 (got {limit})")
    return Control(cmd, stream, limit)


def _decode_fill(m: Map) -> FillMsg:
    sid = _stream_id(m, "fill")
    seq = _get(m, "seq", int, "fill")
    angles = _f32(m, "angles", "fill", None)
    assert angles is not None
    n = angles.size
    status = _get(m, "status", str, "fill")
    if status not in STATUSES:
        raise WireError("bad_status", f"fill status must be one of {list(STATUSES)} (got {status[:40]!r})", sid, seq)
    style = _f32(m, "style", "fill", None, optional=True)
    phase = _get(m, "phase", (int, float), "fill", optional=True)
    pos = _f32(m, "positions", "fill", None, optional=True)
    if pos is not None:
        if pos.size % 3:
            raise WireError("bad_length", f"fill field 'positions' must hold 3 float32 per joint (got {pos.size})", sid, seq)
        pos = pos.reshape(-1, 3)
    return FillMsg(sid, seq, _number(m, "t", "fill"), angles, _mask(m, "filled", "fill", n),  # type: ignore[arg-type]
                   _f32(m, "std", "fill", n), status, _get(m, "model", str, "fill"),  # type: ignore[arg-type]
                   _get(m, "proc_us", int, "fill"), style, None if phase is None else float(phase),
                   _get(m, "gap", int, "fill", optional=True) or 0, pos)


def _decode_ack(m: Map) -> HelloAck:
    sid = _stream_id(m, "hello-ack")
    return HelloAck(sid, _get(m, "model", str, "hello-ack"), _names(m.get("channels"), "channels", "hello-ack", sid),
                    list(_get(m, "passthrough", list, "hello-ack", optional=True) or []),
                    list(_get(m, "missing", list, "hello-ack", optional=True) or []),
                    _get(m, "joints", list, "hello-ack", optional=True), _get(m, "parents", list, "hello-ack", optional=True))


def _decode_drop(m: Map) -> Drop:
    return Drop(_stream_id(m, "drop"), _get(m, "seq", int, "drop"), _get(m, "reason", str, "drop"))


def _decode_control_reply(m: Map) -> ControlReply:
    return ControlReply(_get(m, "cmd", str, "control-reply"), _get(m, "ok", bool, "control-reply"),
                        _get(m, "result", dict, "control-reply", optional=True) or {},
                        _get(m, "error", str, "control-reply", optional=True))


def _decode_error(m: Map) -> ErrorMsg:
    return ErrorMsg(_get(m, "reason", str, "error"), _get(m, "detail", str, "error"),
                    _get(m, "stream", str, "error", optional=True), _get(m, "seq", int, "error", optional=True))


def _decode_bundle(m: Map) -> Bundle:
    frames = _get(m, "frames", list, "frames")
    if not 0 < len(frames) <= MAX_BUNDLE:
        raise WireError("bad_length", f"frames field 'frames' must hold 1..{MAX_BUNDLE} frames (got {len(frames)})")
    block = read_block(frames)
    if block is not None:  # the usual bundle: read as arrays at once (daemon/block.py)
        return BlockBundle(block)
    items: list[Frame | WireError] = []
    for i, f in enumerate(frames):
        if type(f) is not dict:
            items.append(WireError("not_a_map", f"frames[{i}] must be a map (got {type(f).__name__})"))
            continue
        typ, v = f.get("type", "frame"), f.get("v", SCHEMA_VERSION)
        if typ != "frame" or v != SCHEMA_VERSION or isinstance(v, bool):
            items.append(WireError("bad_type", f"frames[{i}] must be a frame of schema {SCHEMA_VERSION} "
                                                f"(got type {typ!r:.40}, v {v!r:.20})", _sid(f), _seq(f)))
            continue
        try:
            items.append(_decode_frame(f))
        except WireError as e:
            items.append(e)
        except Exception as e:  # noqa: BLE001 - same guarantee as decode(): one element's oddity is its own error
            items.append(WireError("malformed", f"frames[{i}] could not be read ({type(e).__name__})", _sid(f), _seq(f)))
    return Bundle(items)


_ANSWERS = ("fill", "drop", "error")


def _decode_replies(m: Map) -> Replies:
    replies = _get(m, "replies", list, "replies")
    items: list[Message] = []
    for i, r in enumerate(replies):
        typ = r.get("type") if type(r) is dict else None
        if typ not in _ANSWERS:
            raise WireError("bad_type", f"replies[{i}] must be one of {list(_ANSWERS)} (got {typ!r:.40})")
        items.append(_DECODERS[typ](r))
    return Replies(items)


_DECODERS: dict[str, Callable[[Map], Message]] = {
    "frame": _decode_frame,
    "frames": _decode_bundle,
    "replies": _decode_replies,
    "hello": _decode_hello,
    "control": _decode_control,
    "fill": _decode_fill,
    "hello-ack": _decode_ack,
    "drop": _decode_drop,
    "control-reply": _decode_control_reply,
    "error": _decode_error,
}


def decode(data: bytes, max_bytes: int = MAX_MESSAGE_BYTES) -> Message:
    """Bytes -> message object.  Raises WireError (only) for anything unusable.

    The size cap is checked before msgpack sees the bytes, and msgpack's own limits stop a
    small message from declaring a huge container.
    """
    return decode_map(unpack(data, max_bytes))


def unpack(data: bytes, max_bytes: int = MAX_MESSAGE_BYTES) -> Map:
    """The first half of :func:`decode`: bytes -> the msgpack map, unchecked beyond being one.
    Raises WireError.  The daemon unpacks a whole burst first to see which frames a newer one
    of the same stream supersedes (:func:`frame_key`), and decodes those after it served."""
    if len(data) > max_bytes:
        raise WireError("too_large", f"message is {len(data)} bytes, the limit is {max_bytes}")
    try:
        m = msgpack.unpackb(
            data, raw=False, strict_map_key=False, use_list=True,
            max_str_len=max_bytes, max_bin_len=max_bytes, max_array_len=MAX_CHANNELS + 16,
            # any number of (unknown, ignored) keys up to the byte cap: a key and its value take
            # at least a byte each, so a map declaring more than max_bytes // 2 cannot be real
            max_map_len=max_bytes // 2, max_ext_len=0,
        )
    except (ValueError, TypeError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError,
            UnicodeDecodeError, OverflowError) as e:
        raise WireError("not_msgpack", f"{len(data)} bytes are not one msgpack value ({type(e).__name__}: {str(e)[:80]})") from None
    except Exception as e:  # noqa: BLE001 - msgpack raises assorted errors on hostile input; none may escape
        raise WireError("not_msgpack", f"{len(data)} bytes are not one msgpack value ({type(e).__name__})") from None
    if not isinstance(m, dict):
        raise WireError("not_a_map", f"message must be a msgpack map (got {type(m).__name__})")
    return m


def frame_key(m: Map) -> tuple[str, int] | None:
    """(stream, seq) of a map that claims to be a v1 ``frame`` with usable ids, else None.  Only
    the ids are looked at: the frame may still fail :func:`decode_map`."""
    if m.get("type") != "frame" or m.get("v") != SCHEMA_VERSION:
        return None
    sid, seq = m.get("stream"), m.get("seq")
    if type(sid) is str and type(seq) is int:
        return sid, seq
    return None


def decode_map(m: Map) -> Message:
    """The second half of :func:`decode`: a map from :func:`unpack` -> message object."""
    v = m.get("v")
    if v != SCHEMA_VERSION or isinstance(v, bool):
        raise WireError("version", f"schema version must be {SCHEMA_VERSION} (got {v!r:.40})", _sid(m), _seq(m))
    typ = m.get("type")
    if not isinstance(typ, str) or typ not in _DECODERS:
        raise WireError("unknown_type", f"message type must be one of {sorted(_DECODERS)} (got {typ!r:.40})",
                        _sid(m), _seq(m))
    try:
        return _DECODERS[typ](m)
    except WireError:
        raise
    except Exception as e:  # noqa: BLE001 - a decoder bug must still come out as a counted rejection
        raise WireError("malformed", f"{typ} could not be read ({type(e).__name__}: {str(e)[:80]})", _sid(m), _seq(m)) from None


