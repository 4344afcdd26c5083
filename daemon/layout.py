"""Decode, the usual way again: a ``frames`` bundle read through its sender's layout, without
msgpack building a map per frame (issue 19's vectorised wire path).

A capture system sends the same bundle every capture instant: the same streams in the same
order, the same keys, the same widths; only each frame's seq, t, angle bytes and mask bytes
change.  Once such a bundle has been read the usual way (msgpack, then
:func:`daemon.block.read_block` accepted it), :meth:`Layouts.learn` packs the map it decoded
to again, piece by piece (msgpack's encoding is canonical: the same map, the same bytes), and
keeps where those four fields lie, if the pieces give back exactly the bytes received.  The
next bundle of that sender with the same length is then read by one compiled call
(:func:`_read`): every byte outside the four fields must equal the layout's (so the message is
the same map with only those values changed: what msgpack would decode it to is known), the
seqs and stamps are read as big-endian integers and doubles, the angle and mask bytes copied
into the block's (n, C) arrays, and the values checked as :func:`read_block` checks them (a seq
at most MAX_SEQ, stamps finite, no infinity where no mask came, mask bytes 0 or 1 and the values
finite where observed).  Anything else returns None and the message takes the usual way, which
names what is wrong: the answers are the same either way (tests/test_daemon_layout.py).

A seq under 128 is msgpack's type byte itself (a positive fixint): that byte must then stay
under 0x80.  Where a seq's width changes (at 128, 256, 65536, ...) the bundle's length does and
its new layout is learned from the next bundle read the usual way.  Without the compiler (``LACUNA_NO_JIT=1``)
every bundle does.  Layouts are kept per sender (``daemon.session.principal``) and length, a
few at a time.
"""
from __future__ import annotations

from typing import Any

import msgpack
import numpy as np

from daemon.block import read_block
from daemon.schema import F32, FrameBlock
from lacuna import jit

KEEP = 16  # layouts kept (a studio's senders send one or a few)
TRIED = 256  # (sender, length) pairs that could not be learned, remembered so as not to try each bundle

_SEQ_WIDTH = {0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8}  # uint8 .. uint64: the payload after the type byte
_FLOAT64 = 0xCB
_U8 = np.dtype(np.uint8)


class Layout:
    """Where a learned bundle's variable fields lie (byte offsets of their payloads)."""

    __slots__ = ("length", "template", "fixed", "seq_at", "seq_width", "t_at", "angles_at", "mask_at", "C", "sids")

    def __init__(self, length: int, template: np.ndarray, fixed: np.ndarray, seq_at: list[int], seq_width: list[int],
                 t_at: list[int], angles_at: list[int], mask_at: list[int], C: int, sids: list[str]):
        self.length = length
        self.template = template  # the learned bytes (uint8)
        self.fixed = fixed  # (k, 2) [start, stop) ranges that must equal the template
        self.seq_at = np.array(seq_at, np.int64)
        self.seq_width = np.array(seq_width, np.int64)
        self.t_at = np.array(t_at, np.int64)
        self.angles_at = np.array(angles_at, np.int64)
        self.mask_at = np.array(mask_at, np.int64)  # empty: the bundle comes without masks
        self.C = C
        self.sids = sids


class Layouts:
    """The layouts of one daemon's senders (part of its dispatcher's state)."""

    def __init__(self) -> None:
        self.on = jit.enabled()
        self.known: dict[tuple[Any, int], Layout] = {}
        self.tried: set[tuple[Any, int]] = set()
        self.hits = 0
        if self.on:  # compiled (or loaded from numba's cache) now, at start, not on a studio's second bundle
            z, e = np.zeros(1, _U8), np.zeros(0, np.int64)  # (the received bytes are read-only: a type of their own)
            _read(np.frombuffer(bytes(1), _U8), z, np.zeros((1, 2), np.int64), e, e, e, e, e, 0, np.zeros((0, 0), _U8),
                  np.zeros((0, 0), _U8), e, np.zeros(0, np.float64))

    def read(self, data: bytes, who: Any, max_bytes: int | None = None) -> FrameBlock | None:
        """The bundle ``data`` from ``who`` as a block, if it matches a layout learned from them, is
        at most ``max_bytes`` long (the daemon's cap, which a reload may lower) and its values pass
        :func:`read_block`'s checks; else None (nothing learned or changed)."""
        lay = self.known.get((who, len(data)))
        if lay is None or (max_bytes is not None and len(data) > max_bytes):
            return None
        n, C = len(lay.sids), lay.C
        values = np.empty((n, 4 * C), _U8)
        masked = len(lay.mask_at) > 0
        mask = np.empty((n if masked else 0, C), _U8)
        seqs = np.empty(n, np.int64)
        stamps = np.empty(n, np.float64)
        if _read(np.frombuffer(data, _U8), lay.template, lay.fixed, lay.seq_at, lay.seq_width, lay.t_at, lay.angles_at,
                 lay.mask_at, C, values, mask, seqs, stamps):
            return None
        v = values.view(F32)
        v.flags.writeable = False  # (as read_block's: a view of the received bytes there)
        m = mask.view(np.bool_) if masked else None
        if m is not None:
            m.flags.writeable = False
        self.hits += 1
        return FrameBlock(lay.sids, seqs.tolist(), stamps.tolist(), v, m)

    def learn(self, data: bytes, msg: dict[str, Any], who: Any) -> bool:
        """Keep ``data``'s layout (``msg``: the map msgpack decoded it to), if it is a bundle
        :func:`read_block` accepts, every seq is at least 256 and the map packs back to exactly
        ``data``.  Each (sender, length) is tried once.  True: learned."""
        key = (who, len(data))
        if not self.on or key in self.known or key in self.tried:
            return False
        if len(self.tried) >= TRIED:
            self.tried.clear()
        self.tried.add(key)
        frames = msg.get("frames")
        if type(frames) is not list or read_block(frames) is None:
            return False
        lay = _layout(data, msg, frames)
        if lay is None:
            return False
        if len(self.known) >= KEEP:
            self.known.clear()
        self.known[key] = lay
        return True

    def forget(self, who: Any) -> None:
        """A sender's layouts go (the connection closed, say); harmless if it had none."""
        for key in [k for k in self.known if k[0] == who]:
            del self.known[key]


def _layout(data: bytes, msg: dict[str, Any], frames: list[dict[str, Any]]) -> Layout | None:
    """The layout of ``data``, built by packing ``msg`` again piece by piece; None where a piece
    is not as the layout needs (a seq under 256, a t that is not a double) or the pieces do not
    give back ``data`` exactly."""
    head = msgpack.Packer(use_bin_type=True)
    pack = head.pack
    out = bytearray(head.pack_map_header(len(msg)))
    var: list[tuple[int, int]] = []  # [start, stop) of every variable payload, in order
    seq_at: list[int] = []
    seq_width: list[int] = []
    t_at: list[int] = []
    angles_at: list[int] = []
    mask_at: list[int] = []
    sids: list[str] = []
    C = -1
    for k, v in msg.items():
        out += pack(k)
        if k != "frames":
            out += pack(v)
            continue
        out += head.pack_array_header(len(v))
        for f in frames:
            out += head.pack_map_header(len(f))
            for fk, fv in f.items():
                out += pack(fk)
                at, b = len(out), pack(fv)
                out += b
                if fk == "seq":
                    if b[0] < 0x80:  # a positive fixint: the value is the type byte (width 0 below)
                        seq_at.append(at)
                        seq_width.append(0)
                        var.append((at, at + 1))
                        continue
                    w = _SEQ_WIDTH.get(b[0])
                    if w is None:
                        return None
                    seq_at.append(at + 1)
                    seq_width.append(w)
                    var.append((at + 1, at + 1 + w))
                elif fk == "t":
                    if b[0] != _FLOAT64:
                        return None
                    t_at.append(at + 1)
                    var.append((at + 1, at + 9))
                elif fk in ("angles", "observed"):
                    start = at + len(b) - len(fv)
                    (angles_at if fk == "angles" else mask_at).append(start)
                    var.append((start, start + len(fv)))
                    if fk == "angles":
                        C = len(fv) // 4
                elif fk == "stream":
                    sids.append(fv)
    if bytes(out) != data or not (len(seq_at) == len(t_at) == len(angles_at) == len(sids) == len(frames)) \
            or len(mask_at) not in (0, len(frames)) or C <= 0:
        return None
    fixed: list[tuple[int, int]] = []
    pos = 0
    for a, b in sorted(var):
        if a > pos:
            fixed.append((pos, a))
        pos = b
    if pos < len(data):
        fixed.append((pos, len(data)))
    return Layout(len(data), np.frombuffer(data, _U8).copy(), np.array(fixed, np.int64).reshape(-1, 2), seq_at, seq_width,
                  t_at, angles_at, mask_at, C, sids)


def _read_py(b: Any, template: Any, fixed: Any, seq_at: Any, seq_width: Any, t_at: Any, angles_at: Any, mask_at: Any, C: int,
             values: Any, mask: Any, seqs: Any, stamps: Any) -> int:  # pragma: no cover - compiled
    """The compiled read (see the module doc); returns 0 (read), 1 (not this layout: a fixed byte
    differs) or 2 (a value :func:`read_block` would refuse)."""
    for r in range(fixed.shape[0]):
        for i in range(fixed[r, 0], fixed[r, 1]):
            if b[i] != template[i]:
                return 1
    n = seq_at.shape[0]
    for i in range(n):
        q = np.uint64(0)
        if seq_width[i] == 0:  # a positive fixint: anything from 0x80 up is another type (a map, say)
            if b[seq_at[i]] >= 0x80:
                return 1
            q = np.uint64(b[seq_at[i]])
        for j in range(seq_width[i]):
            q = (q << np.uint64(8)) | np.uint64(b[seq_at[i] + j])
        if q >= np.uint64(9223372036854775808):  # over MAX_SEQ (2**63 - 1)
            return 2
        seqs[i] = np.int64(q)
        u = np.uint64(0)
        for j in range(8):
            u = (u << np.uint64(8)) | np.uint64(b[t_at[i] + j])
        if (u & np.uint64(0x7FF0000000000000)) == np.uint64(0x7FF0000000000000):  # inf or NaN: not finite
            return 2
        stamps[i] = u  # (stamps: the float64s' bits, as they came)
    masked = mask_at.shape[0] > 0
    for i in range(n):
        a = angles_at[i]
        for c in range(4 * C):
            values[i, c] = b[a + c]
        if masked:
            o = mask_at[i]
            for c in range(C):
                x = b[o + c]
                if x > 1:
                    return 2
                mask[i, c] = x
        for c in range(C):  # (little-endian float32: the exponent is byte 3's low 7 bits and byte 2's top bit)
            k = a + 4 * c
            if (b[k + 3] & 0x7F) == 0x7F and b[k + 2] >= 0x80:  # exponent all ones: inf or NaN
                if masked:
                    if mask[i, c]:
                        return 2  # observed and not finite
                elif (b[k + 2] & 0x7F) == 0 and b[k + 1] == 0 and b[k] == 0:
                    return 2  # infinity (NaN means missing)
    return 0


_read_kernel = jit.jit(_read_py)


def _read(b: np.ndarray, template: np.ndarray, fixed: np.ndarray, seq_at: np.ndarray, seq_width: np.ndarray, t_at: np.ndarray,
          angles_at: np.ndarray, mask_at: np.ndarray, C: int, values: np.ndarray, mask: np.ndarray, seqs: np.ndarray,
          stamps: np.ndarray) -> int:
    return int(_read_kernel(b, template, fixed, seq_at, seq_width, t_at, angles_at, mask_at, C, values, mask, seqs,
                            stamps.view(np.uint64)))
