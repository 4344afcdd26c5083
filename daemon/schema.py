"""Wire schema v1: the message types, their limits and the one error they raise.  No code.

Every message is one msgpack map with ``"v": 1`` and a ``"type"``.  Arrays travel as raw
little-endian bytes (float32 angles/std, one uint8 per channel for masks), so a frame of C
channels costs 4*C bytes of angles whatever the client language.  The full schema, with
examples, is in docs/PROTOCOL.md; this module is its executable form.

daemon/decode.py turns bytes into these (or a :class:`WireError`), daemon/pack.py turns them
back into bytes; daemon/wire.py is the one name the rest of the project imports them by.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

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


@dataclass(slots=True)
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


@dataclass(slots=True)
class FillMsg:
    """The filled frame, in the stream's channel order.

    angles, std : (C,) float32;  filled : (C,) bool, True where the daemon filled the value.
    style : (n_styles,) float32 posterior or None;  phase : gait phase in [0, 1) or None.
    gap : number of frames predicted (never received) just before this one.
    proc_us : microseconds from receipt of the frame to sending this reply (a frame that landed
        during a rehearsal, daemon/prewarm.py, is received at the rehearsal's start: daemon/wait.py).
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


@dataclass(slots=True)
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
class FrameBlock:
    """n frames of one width C, row i being element i of the bundle."""

    sids: list[str]
    seqs: list[int]
    stamps: list[float]
    values: np.ndarray  # (n, C) float32, read-only (a view of the received bytes)
    mask: np.ndarray | None  # (n, C) bool, or None: observed = finite

    def __len__(self) -> int:
        return len(self.sids)

    def observed(self) -> np.ndarray:
        """(n, C) bool: the mask, or where the values are finite."""
        return np.isfinite(self.values) if self.mask is None else self.mask

    def frames(self) -> list[Frame]:
        """One :class:`Frame` per row (angles and observed are row views, nothing copied)."""
        v, m = self.values, self.mask
        if m is None:
            return [Frame(sid, seq, t, v[i], None) for i, (sid, seq, t) in enumerate(zip(self.sids, self.seqs, self.stamps))]
        return [Frame(sid, seq, t, v[i], m[i]) for i, (sid, seq, t) in enumerate(zip(self.sids, self.seqs, self.stamps))]


@dataclass
class Bundle:
    """Several streams' frames in one message (``type: frames``), as a capture system that
    tracks several performers has them: one capture instant, one message.  Each element is read
    on its own: a malformed one is a :class:`WireError` in ``items`` (answered with an error)
    and costs none of the others.  ``block``: the same frames as arrays (daemon/block.py), when
    the bundle was a regular one (every element a well-formed frame of one width)."""

    items: list[Frame | WireError]
    block: FrameBlock | None = field(default=None, compare=False, repr=False)


@dataclass
class Replies:
    """The answers to a bundle's frames (``type: replies``): fills, drops and errors, each the
    message it would have been on its own; match them to frames by stream and seq."""

    items: list[Message]


Message = Hello | HelloAck | Frame | FillMsg | Drop | Control | ControlReply | ErrorMsg | Bundle | Replies
