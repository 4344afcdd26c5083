"""A bundle's frames as arrays (:class:`daemon.schema.FrameBlock`): one pass over the received element maps gives the stream ids,
seqs and stamps, an (n, C) float32 values matrix and an (n, C) bool mask matrix (None: every
element came without a mask, observed = finite), checked as arrays at once.

This is the decode side of the daemon's vectorised wire path: the values of a tick's bundle
are one buffer (the received bytes joined), every :class:`Frame` a row view of it, and the
scheduler stacks a step group's inputs from the block's rows instead of from n separate arrays
(daemon/scheduler.py ``model_inputs``).  :func:`read_block` only accepts what the
element-by-element path (daemon/decode.py) would accept unchanged, and returns None for
anything else, which then takes that path and gets its named error.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from daemon.schema import (
    F32,
    MAX_CHANNELS,
    MAX_SEQ,
    MAX_STREAM_ID,
    SCHEMA_VERSION,
    Bundle,
    Frame,
    FrameBlock,
    WireError,
)

_ADD = np.add.reduce
_PINF, _NINF = np.array([np.inf], F32).tobytes(), np.array([-np.inf], F32).tobytes()


def no_inf(b: bytes) -> bool:
    """True only if the float32 bytes ``b`` hold no infinity: each infinity has one bit pattern,
    so bytes that contain neither pattern anywhere hold none (a byte search, no array).  False
    may be a false alarm (the pattern across two values): the caller then checks with numpy."""
    return b.find(_PINF) < 0 and b.find(_NINF) < 0


def read_block(frames: list[Any]) -> FrameBlock | None:
    """The usual bundle (the daemon's hot path): every element a plain well-formed frame of one
    width, all with an observed mask or all without, as a capture system sends them.  The angle
    (and mask) bytes of all elements are checked as (n, C) arrays at once.  Anything else
    returns None and takes the element-by-element path, which names what is wrong."""
    if not frames:
        return None
    ab: list[bytes] = []
    mb: list[bytes] = []
    sids: list[str] = []
    seqs: list[int] = []
    stamps: list[float] = []
    first = frames[0]
    masked = type(first) is dict and first.get("observed") is not None
    nbytes = -1
    for f in frames:
        if type(f) is not dict:
            return None
        get = f.get
        sid, seq, t, b, ob = get("stream"), get("seq"), get("t"), get("angles"), get("observed")
        if not (type(sid) is str and 0 < len(sid) <= MAX_STREAM_ID and type(seq) is int and 0 <= seq <= MAX_SEQ
                and type(t) is float and type(b) is bytes
                and get("type", "frame") == "frame" and get("v", SCHEMA_VERSION) is SCHEMA_VERSION):
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
        sids.append(sid)
        seqs.append(seq)
        stamps.append(t)
    n, width = len(sids), nbytes // 4
    joined = b"".join(ab)
    values = np.frombuffer(joined, dtype=F32).reshape(n, width)
    mask = None
    if masked:
        masks = b"".join(mb)
        if masks.translate(None, b"\x00\x01"):  # a byte other than 0/1
            return None
        mask = np.frombuffer(masks, dtype=np.bool_).reshape(n, width)
        # finite exactly where observed: the float64 sum of each row's observed values is finite iff all are
        if not np.isfinite(_ADD(values, axis=1, where=mask, dtype=np.float64)).all():
            return None
    elif not no_inf(joined) and np.isinf(values).any():  # NaN means missing; infinity is an error the slow path names
        return None
    if not (all(map(math.isfinite, stamps)) and all(map(str.isprintable, sids))):
        return None
    return FrameBlock(sids, seqs, stamps, values, mask)


class BlockBundle(Bundle):
    """A regular bundle (``block`` is set): its ``items``, one :class:`Frame` per row, are made
    only when something asks for them (the daemon's array path, daemon/blockpath.py, never does)."""

    def __init__(self, block: FrameBlock):  # (not the dataclass's: items come from the block)
        self.block: FrameBlock = block
        self._items: list[Frame | WireError] | None = None

    @property
    def items(self) -> list[Frame | WireError]:
        if self._items is None:
            self._items = list(self.block.frames())
        return self._items

    @items.setter
    def items(self, v: list[Frame | WireError]) -> None:
        self._items = v
