"""An OSC bundle of frames as arrays (issue 19's vectorised wire path, for OSC as daemon/block.py
is for ZeroMQ's ``frames``), and a bundle's fills back to OSC datagrams from their maps.

:func:`read` walks the bundle's elements as :func:`daemon.osc.decode_bundle` does, but reads a
frame element in its usual form (``/lacuna/frame`` with tags ``,s`` ``i|h`` ``f|d`` ``f...f``, or
``/lacuna/frame/masked`` with two blobs, exactly as long as its tags say) with a few slices and
one ``struct`` call instead of python-osc's loop per argument, and the values of all of them as
one (n, C) array.  Every other element is given to :func:`daemon.osc.decode`, the row path's own
decoder: an element it refuses is kept as that very error (rejected and counted by the caller, the
others served), and anything it accepts that is not such a frame (a hello, a frame typed some
other way, a nested bundle) makes :func:`read` return None: the row path takes the whole bundle.
So a frame accepted here is one the row path accepts with the same stream, seq, stamp and values,
and the block holds only what :func:`daemon.block.read_block` would (one width, all masked or
none, observed values finite).

:func:`fill_datagram` is :func:`daemon.osc.encode` of a fill for the maps daemon/tickblock.py
builds (the same bytes: tests/test_daemon_wire_block_osc.py); :func:`send_fills` sends a
bundle's fills as Transports.send sends each (its datagram, then PUB).
"""
from __future__ import annotations

import math
import struct
from typing import Any

import numpy as np

from daemon import blockpath, osc, wire
from daemon.schema import F32, MAX_BUNDLE, MAX_CHANNELS, MAX_SEQ, MAX_STREAM_ID, FrameBlock
from daemon.session import principal

_FRAME = b"/lacuna/frame\0\0\0"
_MASKED = b"/lacuna/frame/masked\0\0\0\0"
_PINF, _NINF = b"\x7f\x80\x00\x00", b"\xff\x80\x00\x00"  # float32 infinities, big-endian
_ADD = np.add.reduce
_F64 = np.dtype(np.float64)
_BE4 = np.dtype(">f4")
_SEQ = {105: (">i", 4), 104: (">q", 8)}  # tag i, h
_T = {102: (">f", 4), 100: (">d", 8)}  # tag f, d
_FS: dict[int, bytes] = {}  # C -> b"f" * C


def _pad(i: int) -> int:
    return (i // 4 + 1) * 4  # past a string's null and its padding


def _frame(el: bytes) -> tuple[str, int, float, bytes, bytes | None] | None:
    """(stream, seq, t, value bytes, mask bytes or None) of a frame element in its usual form
    (values: big-endian float32 for /lacuna/frame, the blob as sent for /lacuna/frame/masked),
    or None: anything else, which the row path's decoder reads."""
    masked = el.startswith(_MASKED)
    if not masked and not el.startswith(_FRAME):
        return None
    i = 24 if masked else 16
    if el[i:i + 2] != b",s":
        return None
    tend = el.find(b"\0", i, i + MAX_CHANNELS + 8)
    if tend < 0:
        return None
    sq, tt = _SEQ.get(el[i + 2]), _T.get(el[i + 3]) if tend > i + 3 else None
    if sq is None or tt is None:
        return None
    C = tend - i - 4
    if masked:
        if el[i + 4:tend] != b"bb":
            return None
    elif C < 1 or el[i + 4:tend] != (_FS.get(C) or _FS.setdefault(C, b"f" * C)):
        return None
    j = _pad(tend)
    e = el.find(b"\0", j, j + osc.MAX_STRING + 1)
    if e <= j:
        return None
    try:
        sid = el[j:e].decode()
    except UnicodeDecodeError:
        return None
    j = _pad(e)
    if len(el) < j + sq[1] + tt[1]:
        return None
    seq = struct.unpack_from(sq[0], el, j)[0]
    j += sq[1]
    t = struct.unpack_from(tt[0], el, j)[0]
    j += tt[1]
    if not (0 < len(sid) <= MAX_STREAM_ID and 0 <= seq <= MAX_SEQ and math.isfinite(t) and sid.isprintable()):
        return None
    if not masked:
        return (sid, seq, t, el[j:], None) if len(el) == j + 4 * C else None
    blobs = []
    for _ in range(2):
        if len(el) < j + 4:
            return None
        k = int.from_bytes(el[j:j + 4], "big", signed=True)
        if k < 1 or len(el) < j + 4 + k:
            return None
        blobs.append(el[j + 4:j + 4 + k])
        j += 4 + k + (-k % 4)
    a, m = blobs
    if j != len(el) or len(a) % 4 or len(a) > 4 * MAX_CHANNELS or 4 * len(m) != len(a) or m.translate(None, b"\x00\x01"):
        return None
    return sid, seq, t, a, m


Read = tuple[FrameBlock, list[int], list[tuple[int, wire.WireError]]]


def read(data: bytes, max_bytes: int) -> Read | None:
    """The frames of an OSC bundle as one block, each row's place in the bundle, and the refused
    elements (their place, the row path's error for each), or None: the row path reads the
    bundle (module doc)."""
    if len(data) > max_bytes or len(data) < 16 or not data.startswith(osc.BUNDLE_PREFIX):
        return None
    errs: list[tuple[int, wire.WireError]] = []
    got: list[tuple[int, bytes, tuple[str, int, float, bytes, bytes | None]]] = []
    i, n, k = 16, len(data), 0
    while i < n:
        size = int.from_bytes(data[i:i + 4], "big", signed=True) if n - i >= 4 else -1
        if size <= 0 or size % 4 or i + 4 + size > n:
            errs.append((k, osc.element_error(i, size, n)))
            break
        el = data[i + 4:i + 4 + size]
        i += 4 + size
        k += 1
        if k > MAX_BUNDLE:
            return None
        f = _frame(el)
        if f is None:
            if el.startswith(osc.BUNDLE_PREFIX):
                return None
            try:
                osc.decode(el, max_bytes)
            except wire.WireError as e:
                errs.append((k - 1, e))
                continue
            return None  # a message this reader does not take: the row path
        got.append((k - 1, el, f))
    if not got:
        return None
    masked = got[0][2][4] is not None
    nb = len(got[0][2][3])
    if any((f[4] is not None) != masked or len(f[3]) != nb for _, _, f in got):
        return None
    C = nb // 4
    joined = b"".join([f[3] for _, _, f in got])
    if masked:
        values = np.frombuffer(joined, F32).reshape(len(got), C)
        mask = np.frombuffer(b"".join([f[4] for _, _, f in got]), np.bool_).reshape(len(got), C)  # type: ignore[misc]
        bad = ~np.isfinite(_ADD(values, axis=1, where=mask, dtype=np.float64))
    else:
        # as the row path makes them: each float32 through a Python float (a C double) and back
        with np.errstate(invalid="ignore"):  # (a signalling NaN is quieted, as the C cast does)
            values = np.frombuffer(joined, _BE4).astype(_F64).astype(F32).reshape(len(got), C)
        mask = None
        bad = np.isinf(values).any(axis=1) if joined.find(_PINF) >= 0 or joined.find(_NINF) >= 0 else None
    if bad is not None and bad.any():  # an element with a value the row path refuses: its error, the rest kept
        for r in np.flatnonzero(bad).tolist():
            try:
                osc.decode(got[r][1], max_bytes)
            except wire.WireError as e:
                errs.append((got[r][0], e))
                continue
            return None
        keep = np.flatnonzero(~bad)
        if not len(keep):
            return None
        got = [got[r] for r in keep.tolist()]
        values, mask = values[keep], (None if mask is None else mask[keep])
        errs.sort(key=lambda pe: pe[0])
    values.flags.writeable = False
    block = FrameBlock([f[0] for _, _, f in got], [f[1] for _, _, f in got], [f[2] for _, _, f in got], values, mask)
    return block, [p for p, _, _ in got], errs


def take(d: Any, data: bytes, origin: Any, arrived: float) -> bool:
    """An OSC bundle (``data``) through the array path of daemon/blockpath.py, for the dispatcher
    ``d`` (daemon/dispatch.py): its frames taken into their sessions as one block, its refused
    elements answered as the row path answers them.  A block the array path does not cover is
    handed to the row path frame by frame, in the bundle's order, without decoding it again.
    False (nothing done): the row path decodes the bundle."""
    if not d.sessions.block_path:
        return False
    try:
        got = read(data, d.cfg.max_message_bytes)
    except Exception as e:  # noqa: BLE001 - a bug here must cost the fast path only: the row path reads it
        d.metrics.inc("internal_errors")
        d.log("error", "internal_error", where="osc_block", error=f"{type(e).__name__}: {e}"[:300])
        return False
    if got is None:
        return False
    block, pos, errs = got
    d.metrics.inc("osc_bundles_in")
    drops = blockpath.take(d.sessions, block, origin, arrived, principal(origin))
    if drops is None:  # (the row path's messages, as osc.decode_bundle gives them)
        items: list[tuple[int, Any]] = sorted([*zip(pos, block.frames()), *errs], key=lambda pm: pm[0])
    else:
        d.metrics.inc("frames_in", len(block))
        d._conflated += drops  # (a waiting bundle's frames it superseded: after the fills)
        items = errs
    for _, m in items:
        if isinstance(m, wire.WireError):
            d._reject(origin, m.reason, m.detail, m.stream, m.seq)
        else:
            d._dispatch(m, origin, arrived)
    return True


# ---- fills back: osc.encode's bytes from a fill map -----------------------------------------
_HEAD = b"#bundle\0" + (1).to_bytes(8, "big")  # python-osc's IMMEDIATELY
_TAGS: dict[tuple[str, int], bytes] = {}


def _s(x: str) -> bytes:
    b = x.encode()
    return b + b"\0" * (4 - len(b) % 4)


def _tags(head: str, C: int) -> bytes:
    t = _TAGS.get((head, C))
    if t is None:
        t = _TAGS[(head, C)] = _s(head + "f" * C)
    return t


def _floats(b: bytes) -> bytes:
    """float32 bytes as osc.encode writes each value (``struct.pack(">f", float(v))``)."""
    with np.errstate(invalid="ignore"):
        return np.frombuffer(b, F32).astype(_F64).astype(_BE4).tobytes()


def fill_datagram(m: dict[str, Any]) -> bytes:
    """:func:`daemon.osc.encode` of the fill whose map (daemon/pack.py ``fill_map``'s) is ``m``."""
    sid = _s(m["stream"])
    ids = sid + struct.pack(">q", m["seq"])
    C = len(m["angles"]) // 4
    parts = [b"/lacuna/fill\0\0\0\0" + _tags(",shdssii", C) + ids + struct.pack(">d", m["t"]) + _s(m["status"])
             + _s(m["model"]) + struct.pack(">ii", osc.i32(m["proc_us"]), osc.i32(m.get("gap", 0))) + _floats(m["angles"]),
             b"/lacuna/std\0" + _tags(",sh", C) + ids + _floats(m["std"])]
    fb = m["filled"]
    parts.append(b"/lacuna/filled\0\0" + b",shb\0\0\0\0" + ids + struct.pack(">i", len(fb)) + fb + b"\0" * (-len(fb) % 4))
    st = m.get("style")
    if st is not None:
        parts.append(b"/lacuna/style\0\0\0" + _tags(",sh", len(st) // 4) + ids + _floats(st))
    ph = m.get("phase")
    if ph is not None and math.isfinite(ph):
        parts.append(b"/lacuna/phase\0\0\0" + b",shf\0\0\0\0" + ids + struct.pack(">f", float(ph)))
    if m.get("positions") is not None:
        raise ValueError("a fill with positions is encoded from its FillMsg (osc.encode)")
    return _HEAD + b"".join([struct.pack(">i", len(p)) + p for p in parts])


def send_fills(net: Any, origin: Any, maps: list[dict[str, Any]]) -> None:
    """A bundle's fills (maps) to an OSC origin, as Transports.send sends each with ``publish``:
    its datagram to the sender (or osc.send), then on PUB under its stream's topic."""
    pub, pack, udp, addr = net.pub, net._pack, net.udp, net.cfg.osc_send or origin[1]
    for m in maps:
        try:
            udp.sendto(fill_datagram(m), addr)
        except OSError as e:
            net.metrics.inc("send_errors")
            net.log("debug", "send_error", transport="osc", error=str(e))
        if pub is not None:
            net._zmq(pub, [m["stream"].encode(), pack(m)], "pub")
