"""Wire schema v1: msgpack maps <-> message objects.  Pure functions on bytes, no sockets.

Every message is one msgpack map with ``"v": 1`` and a ``"type"``.  Arrays travel as raw
little-endian bytes (float32 angles/std, one uint8 per channel for masks), so a frame of C
channels costs 4*C bytes of angles whatever the client language.  The full schema, with
examples, is in docs/PROTOCOL.md; this module is its executable form.

``decode(data)`` either returns one of the message dataclasses below or raises
:class:`WireError` whose ``reason`` is a short stable code (``not_msgpack``, ``too_large``,
``version``, ``missing_field``, ...) that the daemon counts per reason; it never raises
anything else, whatever bytes arrive.  ``encode(msg)`` is its inverse (fixed key order, so the
same message always gives the same bytes).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Union

import msgpack
import numpy as np

SCHEMA_VERSION = 1
MAX_MESSAGE_BYTES = 1 << 20  # default cap, enforced before unpacking; the config can lower it
MAX_CHANNELS = 4096
MAX_STREAM_ID = 128  # characters
MAX_SEQ = (1 << 63) - 1
MAX_NAME = 256  # characters, channel and model names
MAX_CLAIM = 128  # characters, a hello's claim token
MAX_BUNDLE = 1024  # frames in one ``frames`` message (and answers in one ``replies``)
STATUSES = ("ok", "degraded", "passthrough")
CONTROL_COMMANDS = ("status", "reset", "reload", "list-models", "release")

F32 = np.dtype("<f4")


class WireError(ValueError):
    """A message the daemon cannot use.  ``reason`` is a short code counted in metrics."""

    def __init__(self, reason: str, detail: str, stream: str | None = None, seq: int | None = None):
        self.reason, self.detail, self.stream, self.seq = reason, detail, stream, seq
        super().__init__(f"{reason}: {detail}")


# ---- messages --------------------------------------------------------------------------------
@dataclass
class Hello:
    """Handshake: the studio's channel names for one stream, optionally a model by name."""

    stream: str
    channels: list[str]
    model: str | None = None
    claim: str | None = None  # a secret the client keeps across reconnects: presenting it takes its stream over
    positions: bool = False  # every fill of the stream also carries joint positions (the model's skeleton, FK)


@dataclass
class HelloAck:
    """Answer to a Hello: which model serves the stream and how its channels were mapped.

    passthrough: studio channels the model lacks (returned untouched);
    missing: model channels the studio does not send (always filled, not returned).
    """

    stream: str
    model: str
    channels: list[str]
    passthrough: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    joints: list[str] | None = None  # with hello positions: the joints of the fills' positions, in their order
    parents: list[int] | None = None  # parent index per joint, -1 for a root


@dataclass
class Frame:
    """One captured frame.

    angles : (C,) float32, NaN where missing (unless ``observed`` says otherwise).
    observed : (C,) bool or None.  None means "observed = angles are finite".
    """

    stream: str
    seq: int
    t: float
    angles: np.ndarray
    observed: np.ndarray | None = None


@dataclass
class FillMsg:
    """The filled frame, in the stream's channel order.

    angles, std : (C,) float32;  filled : (C,) bool, True where the daemon filled the value.
    style : (n_styles,) float32 posterior or None;  phase : gait phase in [0, 1) or None.
    gap : number of frames predicted (never received) just before this one.
    proc_us : microseconds from receipt of the frame to sending this reply.
    """

    stream: str
    seq: int
    t: float
    angles: np.ndarray
    filled: np.ndarray
    std: np.ndarray
    status: str
    model: str
    proc_us: int
    style: np.ndarray | None = None
    phase: float | None = None
    gap: int = 0
    positions: np.ndarray | None = None  # (J, 3) float32 metres, for a stream whose hello asked


@dataclass
class Drop:
    """A frame received but not served: ``conflated`` (a newer frame of the stream replaced it),
    ``late`` (older than one already served), ``duplicate``."""

    stream: str
    seq: int
    reason: str


@dataclass
class Control:
    """Control request: status, reset (needs ``stream``), reload, list-models."""

    cmd: str
    stream: str | None = None
    limit: int | None = None  # status: how many streams to detail (default: the daemon's, most recently active first)


@dataclass
class ControlReply:
    cmd: str
    ok: bool
    result: dict[str, Any] = field(default_factory=dict)
    error: str | None = None


@dataclass
class ErrorMsg:
    """Rejection of a message: ``reason`` is the WireError code, ``detail`` says what arrived."""

    reason: str
    detail: str
    stream: str | None = None
    seq: int | None = None


@dataclass
class Bundle:
    """Several streams' frames in one message (``type: frames``), as a capture system that
    tracks several performers has them: one capture instant, one message.  Each element is read
    on its own: a malformed one is a :class:`WireError` in ``items`` (answered with an error)
    and costs none of the others."""

    items: list[Union[Frame, WireError]]


@dataclass
class Replies:
    """The answers to a bundle's frames (``type: replies``): fills, drops and errors, each the
    message it would have been on its own; match them to frames by stream and seq."""

    items: list["Message"]


Message = Union[Hello, HelloAck, Frame, FillMsg, Drop, Control, ControlReply, ErrorMsg, Bundle, Replies]


# ---- decode ----------------------------------------------------------------------------------
def _get(m: dict, key: str, kind: type | tuple[type, ...], what: str, optional: bool = False) -> Any:
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


def _sid(m: dict) -> str | None:
    s = m.get("stream")
    return s if isinstance(s, str) and len(s) <= MAX_STREAM_ID else None


def _seq(m: dict) -> int | None:
    s = m.get("seq")
    return s if isinstance(s, int) and not isinstance(s, bool) and 0 <= s <= MAX_SEQ else None


def _stream_id(m: dict, what: str) -> str:
    s = _get(m, "stream", str, what)
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


def _f32(m: dict, key: str, what: str, n: int | None, optional: bool = False) -> np.ndarray | None:
    b = _get(m, key, bytes, what, optional)
    if b is None:
        return None
    if len(b) % 4 or (n is not None and len(b) != 4 * n) or len(b) > 4 * MAX_CHANNELS:
        want = f"{4 * n}" if n is not None else f"a multiple of 4, at most {4 * MAX_CHANNELS}"
        raise WireError("bad_length", f"{what} field {key!r} must be {want} bytes of float32 (got {len(b)})",
                        _sid(m), _seq(m))
    return np.frombuffer(b, dtype=F32)


def _mask(m: dict, key: str, what: str, n: int, optional: bool = False) -> np.ndarray | None:
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


def _number(m: dict, key: str, what: str) -> float:
    v = _get(m, key, (int, float), what)
    v = float(v)
    if not math.isfinite(v):
        raise WireError("bad_timestamp", f"{what} field {key!r} must be finite (got {v})", _sid(m), _seq(m))
    return v


_ADD = np.add.reduce


def _decode_frame(m: dict) -> Frame:
    # fast path for the common, well-formed frame (the daemon's hot path); anything unusual
    # goes through the checked path below, which names what is wrong
    sid, seq, t, b, ob = m.get("stream"), m.get("seq"), m.get("t"), m.get("angles"), m.get("observed")
    if (type(sid) is str and 0 < len(sid) <= MAX_STREAM_ID and type(seq) is int and 0 <= seq <= MAX_SEQ
            and type(t) is float and math.isfinite(t) and type(b) is bytes and 0 < len(b) <= 4 * MAX_CHANNELS
            and not len(b) % 4 and sid.isprintable()):
        angles = np.frombuffer(b, dtype=F32)
        if ob is None:
            if not np.isinf(angles).any():
                return Frame(sid, seq, t, angles, None)
        # a mask of one 0/1 byte per channel (translate deletes those bytes: nothing may be left)
        elif type(ob) is bytes and 4 * len(ob) == len(b) and not ob.translate(None, b"\x00\x01"):
            observed = np.frombuffer(ob, dtype=np.bool_)
            # one reduction: the float64 sum of the observed values is finite exactly when all of them
            # are (float32 values cannot overflow it; NaN and +-inf propagate)
            if math.isfinite(_ADD(angles, where=observed, dtype=np.float64)):
                return Frame(sid, seq, t, angles, observed)
    return _decode_frame_checked(m)


def _decode_frame_checked(m: dict) -> Frame:
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


def _decode_hello(m: dict) -> Hello:
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


def _decode_control(m: dict) -> Control:
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


def _decode_fill(m: dict) -> FillMsg:
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


def _decode_ack(m: dict) -> HelloAck:
    sid = _stream_id(m, "hello-ack")
    return HelloAck(sid, _get(m, "model", str, "hello-ack"), _names(m.get("channels"), "channels", "hello-ack", sid),
                    list(_get(m, "passthrough", list, "hello-ack", optional=True) or []),
                    list(_get(m, "missing", list, "hello-ack", optional=True) or []),
                    _get(m, "joints", list, "hello-ack", optional=True), _get(m, "parents", list, "hello-ack", optional=True))


def _decode_drop(m: dict) -> Drop:
    return Drop(_stream_id(m, "drop"), _get(m, "seq", int, "drop"), _get(m, "reason", str, "drop"))


def _decode_control_reply(m: dict) -> ControlReply:
    return ControlReply(_get(m, "cmd", str, "control-reply"), _get(m, "ok", bool, "control-reply"),
                        _get(m, "result", dict, "control-reply", optional=True) or {},
                        _get(m, "error", str, "control-reply", optional=True))


def _decode_error(m: dict) -> ErrorMsg:
    return ErrorMsg(_get(m, "reason", str, "error"), _get(m, "detail", str, "error"),
                    _get(m, "stream", str, "error", optional=True), _get(m, "seq", int, "error", optional=True))


def _decode_bundle(m: dict) -> Bundle:
    frames = _get(m, "frames", list, "frames")
    if not 0 < len(frames) <= MAX_BUNDLE:
        raise WireError("bad_length", f"frames field 'frames' must hold 1..{MAX_BUNDLE} frames (got {len(frames)})")
    fast = _bundle_fast(frames)
    if fast is not None:
        return Bundle(fast)  # type: ignore[arg-type]
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
        except Exception as e:  # same guarantee as decode(): one element's oddity is its own error
            items.append(WireError("malformed", f"frames[{i}] could not be read ({type(e).__name__})", _sid(f), _seq(f)))
    return Bundle(items)


def _bundle_fast(frames: list) -> list[Frame] | None:
    """The usual bundle (the daemon's hot path): every element a plain well-formed frame of one
    width, all with an observed mask or all without, as a capture system sends them.  The angle
    (and mask) bytes of all elements are checked as (n, C) arrays at once, and each Frame holds
    its row of them.  Anything else returns None and takes the element-by-element path, which
    names what is wrong."""
    ab: list[bytes] = []
    mb: list[bytes] = []
    head = []
    masked = type(frames[0]) is dict and frames[0].get("observed") is not None
    nbytes = -1
    for f in frames:
        if type(f) is not dict:
            return None
        sid, seq, t, b, ob = f.get("stream"), f.get("seq"), f.get("t"), f.get("angles"), f.get("observed")
        if not (type(sid) is str and 0 < len(sid) <= MAX_STREAM_ID and type(seq) is int and 0 <= seq <= MAX_SEQ
                and type(t) is float and type(b) is bytes
                and f.get("type", "frame") == "frame" and f.get("v", SCHEMA_VERSION) is SCHEMA_VERSION):
            return None
        if len(b) != nbytes:  # the first element sets the width, every other one must have it
            if nbytes >= 0 or not 0 < len(b) <= 4 * MAX_CHANNELS or len(b) % 4:
                return None
            nbytes = len(b)
        if masked:
            if type(ob) is not bytes or 4 * len(ob) != nbytes:
                return None
            mb.append(ob)
        elif ob is not None:
            return None
        ab.append(b)
        head.append((sid, seq, t))
    n, width = len(head), nbytes // 4
    angles = np.frombuffer(b"".join(ab), dtype=F32).reshape(n, width)
    if masked:
        masks = b"".join(mb)
        if masks.translate(None, b"\x00\x01"):  # a byte other than 0/1
            return None
        observed = np.frombuffer(masks, dtype=np.bool_).reshape(n, width)
        # finite exactly where observed: the float64 sum of each row's observed values is finite iff all are
        if not np.isfinite(_ADD(angles, axis=1, where=observed, dtype=np.float64)).all():
            return None
    elif np.isinf(angles).any():  # NaN means missing; infinity is an error the slow path names
        return None
    if not all(math.isfinite(t) and sid.isprintable() for sid, _, t in head):
        return None
    if masked:
        return [Frame(sid, seq, t, angles[i], observed[i]) for i, (sid, seq, t) in enumerate(head)]
    return [Frame(sid, seq, t, angles[i], None) for i, (sid, seq, t) in enumerate(head)]


_ANSWERS = ("fill", "drop", "error")


def _decode_replies(m: dict) -> Replies:
    replies = _get(m, "replies", list, "replies")
    items: list[Message] = []
    for i, r in enumerate(replies):
        typ = r.get("type") if type(r) is dict else None
        if typ not in _ANSWERS:
            raise WireError("bad_type", f"replies[{i}] must be one of {list(_ANSWERS)} (got {typ!r:.40})")
        items.append(_DECODERS[typ](r))
    return Replies(items)


_DECODERS = {
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


def unpack(data: bytes, max_bytes: int = MAX_MESSAGE_BYTES) -> dict:
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
    except Exception as e:  # msgpack raises assorted errors on hostile input; none may escape
        raise WireError("not_msgpack", f"{len(data)} bytes are not one msgpack value ({type(e).__name__})") from None
    if not isinstance(m, dict):
        raise WireError("not_a_map", f"message must be a msgpack map (got {type(m).__name__})")
    return m


def frame_key(m: dict) -> tuple[str, int] | None:
    """(stream, seq) of a map that claims to be a v1 ``frame`` with usable ids, else None.  Only
    the ids are looked at: the frame may still fail :func:`decode_map`."""
    if m.get("type") != "frame" or m.get("v") != SCHEMA_VERSION:
        return None
    sid, seq = m.get("stream"), m.get("seq")
    if type(sid) is str and type(seq) is int:
        return sid, seq
    return None


def decode_map(m: dict) -> Message:
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
    except Exception as e:  # a decoder bug must still come out as a counted rejection
        raise WireError("malformed", f"{typ} could not be read ({type(e).__name__}: {str(e)[:80]})", _sid(m), _seq(m)) from None


# ---- encode ----------------------------------------------------------------------------------
def _b32(a: np.ndarray) -> bytes:
    if type(a) is np.ndarray and a.dtype == F32 and a.flags.c_contiguous:
        return a.tobytes()  # the daemon's own fills arrive like this: no conversion
    return np.ascontiguousarray(a, dtype=F32).tobytes()


def _bmask(a: np.ndarray) -> bytes:
    if type(a) is np.ndarray and a.dtype == np.bool_ and a.flags.c_contiguous:
        return a.tobytes()  # bool is one 0/1 byte each
    return np.ascontiguousarray(a, dtype=bool).astype(np.uint8).tobytes()


def to_map(msg: Message) -> dict[str, Any]:
    """Message object -> the msgpack map (fixed key order)."""
    if isinstance(msg, FillMsg):  # the daemon's hot path: checked first
        d = {"v": 1, "type": "fill", "stream": msg.stream, "seq": msg.seq, "t": msg.t,
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
    if isinstance(msg, Frame):
        d: dict[str, Any] = {"v": 1, "type": "frame", "stream": msg.stream, "seq": msg.seq, "t": msg.t,
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
    return msgpack.packb(to_map(msg), use_bin_type=True)


_PACK = msgpack.Packer(use_bin_type=True)
_REPLIES_HEAD = _PACK.pack_map_header(3) + _PACK.pack("v") + _PACK.pack(SCHEMA_VERSION) + \
    _PACK.pack("type") + _PACK.pack("replies") + _PACK.pack("replies")


def join_replies(bodies: list[bytes]) -> bytes:
    """Encoded answers (each ``encode(msg)``) -> one ``replies`` message, without decoding them:
    a msgpack array is its header followed by its elements' bytes."""
    return _REPLIES_HEAD + _PACK.pack_array_header(len(bodies)) + b"".join(bodies)


def error_for(e: WireError) -> ErrorMsg:
    return ErrorMsg(e.reason, e.detail, e.stream, e.seq)
