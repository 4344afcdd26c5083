"""OSC address space <-> wire messages.  Pure functions on datagram bytes (python-osc parses).

The address space is documented in docs/PROTOCOL.md (## OSC address space).  ``decode``
returns the same message objects as the msgpack decoder (Hello, Frame, Control) or raises
``wire.WireError``; ``encode`` turns a daemon answer into one datagram (a bundle for a fill).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import msgpack
import numpy as np
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message import OscMessage
from pythonosc.osc_message_builder import OscMessageBuilder

from daemon import wire

BUNDLE_PREFIX = b"#bundle\x00"
MAX_DEPTH = 4  # bundles within bundles, at most


def _msg(address: str, args: Sequence[tuple[object, str]]) -> OscMessageBuilder:
    b = OscMessageBuilder(address)
    for v, t in args:
        b.add_arg(v, t)  # type: ignore[arg-type]
    return b


def _str(args: list[Any], i: int, what: str) -> str:
    if i >= len(args) or not isinstance(args[i], str):
        got = type(args[i]).__name__ if i < len(args) else "nothing"
        raise wire.WireError("bad_type", f"OSC {what}: argument {i + 1} must be a string (got {got})")
    return str(args[i])


def _int(args: list[Any], i: int, what: str) -> int:
    if i >= len(args) or not isinstance(args[i], int) or isinstance(args[i], bool):
        got = type(args[i]).__name__ if i < len(args) else "nothing"
        raise wire.WireError("bad_type", f"OSC {what}: argument {i + 1} (seq) must be an int (got {got})")
    return int(args[i])


def _float(args: list[Any], i: int, what: str) -> float:
    if i >= len(args) or isinstance(args[i], bool) or not isinstance(args[i], (int, float)):
        got = type(args[i]).__name__ if i < len(args) else "nothing"
        raise wire.WireError("bad_type", f"OSC {what}: argument {i + 1} (t) must be a number (got {got})")
    return float(args[i])


def decode(data: bytes, max_bytes: int = wire.MAX_MESSAGE_BYTES) -> wire.Message:
    """One OSC datagram -> Hello | Frame | Control.  Raises wire.WireError only."""
    if len(data) > max_bytes:
        raise wire.WireError("too_large", f"datagram is {len(data)} bytes, the limit is {max_bytes}")
    if not data.startswith(b"/"):
        what = "an OSC bundle (decode_bundle reads those)" if data.startswith(BUNDLE_PREFIX) else "not an OSC message"
        raise wire.WireError("not_osc", f"{len(data)} bytes are {what}")
    _precheck(data)
    try:
        m = OscMessage(data)
        addr, args = m.address, list(m.params)
    except Exception as e:  # python-osc raises ParseError and assorted others on bad bytes
        raise wire.WireError("not_osc", f"{len(data)} bytes are not an OSC message ({type(e).__name__})") from None
    try:
        if addr == "/lacuna/frame":
            sid, seq, t = _str(args, 0, addr), _int(args, 1, addr), _float(args, 2, addr)
            vals = args[3:]
            if not vals or len(vals) > wire.MAX_CHANNELS or not all(isinstance(v, float) for v in vals):
                raise wire.WireError("bad_type", f"OSC {addr}: after stream, seq, t come 1..{wire.MAX_CHANNELS} "
                                                 f"float angles (got {len(vals)} values)", sid, seq)
            return _via_wire({"type": "frame", "stream": sid, "seq": seq, "t": t,
                           "angles": np.asarray(vals, dtype=wire.F32).tobytes()})
        if addr == "/lacuna/frame/masked":
            sid, seq, t = _str(args, 0, addr), _int(args, 1, addr), _float(args, 2, addr)
            if len(args) != 5 or not isinstance(args[3], bytes) or not isinstance(args[4], bytes):
                raise wire.WireError("bad_type", f"OSC {addr}: needs stream, seq, t, angles blob, observed blob", sid, seq)
            return _via_wire({"type": "frame", "stream": sid, "seq": seq, "t": t, "angles": args[3], "observed": args[4]})
        if addr in ("/lacuna/hello", "/lacuna/hello/positions"):  # the second: fills carry joint positions
            sid, model = _str(args, 0, addr), _str(args, 1, addr)
            d: dict[str, Any] = {"type": "hello", "stream": sid, "channels": args[2:], "model": model or None}
            if addr == "/lacuna/hello/positions":
                d["positions"] = True
            return _via_wire(d)
        if addr == "/lacuna/reset":
            return wire.Control("reset", _str(args, 0, addr))
    except wire.WireError:
        raise
    except Exception as e:
        raise wire.WireError("malformed", f"OSC {addr} could not be read ({type(e).__name__})") from None
    raise wire.WireError("unknown_type", f"OSC address {addr[:60]!r} is not one of /lacuna/frame, /lacuna/frame/masked, "
                                         f"/lacuna/hello, /lacuna/hello/positions, /lacuna/reset")


def _precheck(data: bytes) -> None:
    """Bound what python-osc's parser (a Python loop per byte of a string, per argument) may be
    given: the address and every string argument at most MAX_STRING bytes, at most
    wire.MAX_CHANNELS + 8 arguments.  Each string's end is found with bytes.find (C speed,
    searched no further than the limit).  Raises WireError("bad_length")."""
    end = data.find(b"\0", 0, MAX_STRING + 1)
    if end < 0:
        if len(data) <= MAX_STRING:
            return  # not terminated at all: python-osc says not_osc
        raise wire.WireError("bad_length", f"OSC address longer than {MAX_STRING} bytes")
    i = (end // 4 + 1) * 4
    if data[i:i + 1] != b",":
        return  # no type tags: python-osc decides what it is
    tend = data.find(b"\0", i, i + wire.MAX_CHANNELS + 10)
    if tend < 0:
        if len(data) < i + wire.MAX_CHANNELS + 10:
            return
        raise wire.WireError("bad_length", f"OSC message with more than {wire.MAX_CHANNELS + 8} arguments")
    tags = data[i + 1:tend]
    last = max(tags.rfind(b"s"), tags.rfind(b"S"))
    i = (tend // 4 + 1) * 4
    for t in tags[:last + 1]:  # (up to the last string argument; frames have one, first)
        if t in _STR:
            e = data.find(b"\0", i, i + MAX_STRING + 1)
            if e < 0:
                if len(data) <= i + MAX_STRING:
                    return
                raise wire.WireError("bad_length", f"OSC string argument longer than {MAX_STRING} bytes")
            i = (e // 4 + 1) * 4
        elif t in _W4:
            i += 4
        elif t in _W8:
            i += 8
        elif t == 98:  # b: blob, size-prefixed and padded
            n = int.from_bytes(data[i:i + 4], "big", signed=True)
            if n < 0:
                return
            i += 4 + n + (-n % 4)
        elif t not in _W0:
            return  # a type python-osc may or may not know: it decides


MAX_STRING = 512  # bytes of an OSC string argument or address (names are at most 256 characters)
_STR, _W4, _W8, _W0 = b"sS", b"ifcrm", b"hdt", b"TFNI[]"


def decode_bundle(data: bytes, max_bytes: int = wire.MAX_MESSAGE_BYTES, depth: int = 0) -> list[wire.Message | wire.WireError]:
    """One OSC bundle datagram -> its messages in order, nested bundles flattened, each what
    :func:`decode` gives for it or the WireError it raised: a malformed element costs only
    itself (an element whose size field is wrong leaves the rest unreadable: one error for
    them).  The timetag is not honoured: the elements are served as they arrive.  Raises
    WireError when the datagram is not a usable bundle at all (too large, too short, nested
    deeper than MAX_DEPTH, more than wire.MAX_BUNDLE messages)."""
    if len(data) > max_bytes:
        raise wire.WireError("too_large", f"datagram is {len(data)} bytes, the limit is {max_bytes}")
    if not data.startswith(BUNDLE_PREFIX) or len(data) < 16:
        raise wire.WireError("not_osc", f"{len(data)} bytes are not an OSC bundle (#bundle, a timetag, elements)")
    if depth >= MAX_DEPTH:
        raise wire.WireError("malformed", f"OSC bundles nested more than {MAX_DEPTH} deep")
    out: list[wire.Message | wire.WireError] = []
    i, n = 16, len(data)
    while i < n:
        size = int.from_bytes(data[i:i + 4], "big", signed=True) if n - i >= 4 else -1
        if size <= 0 or size % 4 or i + 4 + size > n:
            out.append(element_error(i, size, n))
            break
        el = data[i + 4:i + 4 + size]
        i += 4 + size
        try:
            if el.startswith(BUNDLE_PREFIX):
                out.extend(decode_bundle(el, max_bytes, depth + 1))
            else:
                out.append(decode(el, max_bytes))
        except wire.WireError as e:
            if e.reason == "too_large" and el.startswith(BUNDLE_PREFIX):  # over the message cap: the whole is
                raise
            out.append(e)
        if len(out) > wire.MAX_BUNDLE:
            raise wire.WireError("too_large", f"an OSC bundle of more than {wire.MAX_BUNDLE} messages")
    return out


def element_error(i: int, size: int, n: int) -> wire.WireError:
    """A bundle's element at byte ``i`` of ``n`` whose size field (``size``) is wrong."""
    return wire.WireError("malformed", f"OSC bundle element at byte {i} declares {size} bytes with "
                                       f"{n - i - 4} left: the rest of the bundle cannot be read")


def _via_wire(d: dict[str, Any]) -> wire.Message:
    """Validate through the msgpack decoder's rules so both transports check the same things."""
    return wire.decode(msgpack.packb({"v": 1, **d}, use_bin_type=True), 1 << 30)


I32_MAX = 2**31 - 1


def i32(v: int) -> int:
    """An int for an OSC "i" argument: saturated to int32 (a fill's gap after a seq that jumped by
    2^40, a proc_us after a stall), where python-osc would raise inside the tick."""
    return max(-I32_MAX - 1, min(I32_MAX, int(v)))


def encode(msg: wire.Message) -> bytes:
    """A daemon answer -> one OSC datagram."""
    if isinstance(msg, wire.FillMsg):
        bb = OscBundleBuilder(IMMEDIATELY)
        sid, seq = (msg.stream, "s"), (msg.seq, "h")
        bb.add_content(_msg("/lacuna/fill", [sid, seq, (msg.t, "d"), (msg.status, "s"), (msg.model, "s"),
                                             (i32(msg.proc_us), "i"), (i32(msg.gap), "i")]
                            + [(float(v), "f") for v in msg.angles]).build())
        bb.add_content(_msg("/lacuna/std", [sid, seq] + [(float(v), "f") for v in msg.std]).build())
        bb.add_content(_msg("/lacuna/filled", [sid, seq, (np.asarray(msg.filled, np.uint8).tobytes(), "b")]).build())
        if msg.style is not None:
            bb.add_content(_msg("/lacuna/style", [sid, seq] + [(float(v), "f") for v in msg.style]).build())
        if msg.phase is not None and math.isfinite(msg.phase):
            bb.add_content(_msg("/lacuna/phase", [sid, seq, (float(msg.phase), "f")]).build())
        if msg.positions is not None:  # (J, 3) metres, x y z of each joint in the hello-ack's /lacuna/joints order
            bb.add_content(_msg("/lacuna/positions", [sid, seq] + [(float(v), "f") for v in np.ravel(msg.positions)]).build())
        return bb.build().dgram
    if isinstance(msg, wire.HelloAck):
        ack = _msg("/lacuna/hello-ack", [(msg.stream, "s"), (msg.model, "s"), (len(msg.channels), "i"),
                                         (len(msg.passthrough), "i"), (len(msg.missing), "i")]).build()
        if msg.joints is None:
            return ack.dgram
        bb = OscBundleBuilder(IMMEDIATELY)  # a hello that asked for positions: the joints they are of
        bb.add_content(ack)
        bb.add_content(_msg("/lacuna/joints", [(msg.stream, "s")] + [(j, "s") for j in msg.joints]).build())
        bb.add_content(_msg("/lacuna/parents", [(msg.stream, "s")] + [(int(p), "i") for p in msg.parents or ()]).build())
        return bb.build().dgram
    if isinstance(msg, wire.Drop):
        return _msg("/lacuna/drop", [(msg.stream, "s"), (msg.seq, "h"), (msg.reason, "s")]).build().dgram
    if isinstance(msg, wire.ErrorMsg):
        return _msg("/lacuna/error", [(msg.reason, "s"), (msg.detail[:400], "s")]).build().dgram
    if isinstance(msg, wire.ControlReply):
        return _msg("/lacuna/control-reply", [(msg.cmd, "s"), (1 if msg.ok else 0, "i"), (msg.error or "", "s")]).build().dgram
    raise TypeError(f"no OSC form for {type(msg).__name__}")
