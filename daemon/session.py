"""Per-stream sessions: channel mapping, sequence numbers, the one pending frame, counters.

A session holds everything the daemon knows about one performer's stream: which model serves
it, how the studio's channel list maps onto the model's, the filler state, the last sequence
number answered and the last one the filler consumed, the last completed frame (for
hold-last-value when the scheduler degrades), and a single *pending* slot: a newer frame
replaces an older waiting one (conflation), so nothing queues inside the daemon.

Message handling returns the immediate answers (``drop``/``error``/``hello-ack``) as a list of
``(origin, message)``; filled frames come from the scheduler.  No sockets here.

Ownership (docs/PROTOCOL.md, "Stream ownership"): a stream belongs to the principal that opened
it (``who``: a ZeroMQ connection, a CURVE key, an OSC source address; the daemon says which).
Frames, ``hello`` and ``reset`` for a stream owned by someone else are refused ``not_owner``
unless the stream's owner has been silent for ``idle_s`` (then it is free, as if it had expired),
a ``hello`` carries the claim token the stream was opened with (the owner reconnecting), or, for
``reset``, the caller is an operator.  ``who=None`` (in-process callers) skips the checks.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from daemon import wire
from lacuna.filler import FillerState, Model

Origin = tuple[Any, ...]  # (transport name, address): ("router", envelope) | ("router", envelope, "bundle") | ("pull", None) | ("osc", (host, port))
Out = list[tuple[Origin, wire.Message]]

COUNTERS = ("frames_in", "frames_out", "dropped_conflated", "dropped_late", "dropped_duplicate", "dropped_reset",
            "dropped_overdue", "over_budget", "rejected", "degraded", "held", "predicted", "restarts",
            "foreign", "waited")
# foreign: frames/hellos/resets for this stream refused because they came from someone else;
# waited: frames that reached the daemon WAIT_REPORT_S or more later than their capture
# timestamp says they should have, judged against the stream's quickest delivery (see frame())
WAIT_REPORT_S = 0.05
WAIT_PLAUSIBLE_S = 30.0  # more than this is taken for a jump of the capture clock, not a wait
WAIT_FOLLOW = 1e-4  # how fast the quickest-delivery baseline follows a drift between the clocks


def principal(origin: Origin) -> tuple[Any, ...]:
    """Who sent a message, for stream ownership: the CURVE public key when the ROUTER socket is
    a CURVE server (the transport hangs it on the envelope as ``.key``), else the ROUTER
    connection (its routing id); an OSC source address; PULL and SUB senders together as one."""
    kind = origin[0]
    if kind == "router":
        env = origin[1]
        key = getattr(env, "key", None)
        return ("key", key) if key is not None else ("conn", env[0])
    if kind == "osc":
        return ("osc", origin[1][0], origin[1][1])
    return (kind,)


@dataclass
class Pending:
    frame: wire.Frame
    origin: Origin
    arrived: float  # time.perf_counter() at receipt


@dataclass
class Mapping:
    """studio frame (n_in,) -> model frame (n_model,): model[m_idx] = studio[s_idx]."""

    channels: list[str]
    s_idx: np.ndarray
    m_idx: np.ndarray
    passthrough: list[str]
    missing: list[str]
    n_model: int
    # (set once from the above, plain attributes: read for every frame; a mapping is never
    # changed, a new one is built)
    n_in: int = field(init=False)
    # the studio sends exactly the model's channels in the model's order (the usual case):
    # frames need no reordering either way
    identity: bool = field(init=False)

    @classmethod
    def build(cls, studio: list[str], model_channels: list[str]) -> Mapping:
        pos = {c: i for i, c in enumerate(model_channels)}
        s_idx = np.array([i for i, c in enumerate(studio) if c in pos], dtype=np.intp)
        m_idx = np.array([pos[c] for c in studio if c in pos], dtype=np.intp)
        sent = set(studio)
        s_idx.setflags(write=False)   # shared by every stream that sent the same list (SessionTable)
        m_idx.setflags(write=False)
        return cls(list(studio), s_idx, m_idx, [c for c in studio if c not in pos],
                   [c for c in model_channels if c not in sent], len(model_channels))

    def __post_init__(self) -> None:
        n = self.n_model
        self.n_in = len(self.channels)
        self.identity = bool(self.n_in == n and self.s_idx.size == n and (self.s_idx == np.arange(n)).all()
                             and (self.m_idx == np.arange(n)).all())


@dataclass
class Session:
    sid: str
    model_name: str
    model: Model
    mapping: Mapping
    state: FillerState
    last_seq: int | None = None  # last sequence number answered (filled, held, or dropped `overdue`)
    model_seq: int | None = None  # last sequence number the filler state consumed
    last_out: np.ndarray | None = None  # (n_model,) last completed frame, for hold-last-value
    pending: Pending | None = None
    last_active: float = field(default_factory=time.perf_counter)  # (the table's clock)
    held_streak: int = 0
    late_streak: int = 0  # frames in a row answered `overdue`: breaks ties in who goes first
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(COUNTERS, 0))
    order: int = 0  # when its stream id entered the table (a replaced session keeps it)
    t_base: float | None = None  # quickest (arrival - capture t) seen: the stream's delivery baseline
    max_wait_s: float = 0.0
    owner: Any = None  # the principal that opened the stream (None: anyone)
    claim: str | None = None  # the claim token of its hello: a new connection presenting it takes the stream over
    fk: Any = None  # daemon.positions.StreamFK when the hello asked for positions (else no FK work at all)

    def restart(self) -> None:
        """Fresh filter state; the sequence numbering restarts at the next frame."""
        self.state = self.model.stream()
        self.model_seq = None
        self.last_out = None

    def delivered(self, off: float) -> bool:
        """A frame arrived ``off`` = arrival - capture time after it was captured: constant for a
        frame delivered as quickly as ever, more when it waited on its way (a stalled daemon, a
        full socket).  Moves the quickest-delivery baseline; True when the frame waited
        WAIT_REPORT_S or more (counted here; the table counts ``frames_waited``)."""
        b = self.t_base
        if b is None or off < b:
            self.t_base = off
            return False
        w = off - b
        if w > WAIT_PLAUSIBLE_S:  # the capture clock jumped: a new baseline
            self.t_base = off
            return False
        self.t_base = b + w * WAIT_FOLLOW
        if w < WAIT_REPORT_S:
            return False
        self.counts["waited"] += 1
        self.max_wait_s = max(self.max_wait_s, w)
        return True

    # ---- the transitions of a served frame (the scheduler's and the tick's) -------------------
    def count(self, name: str, n: int = 1) -> None:
        self.counts[name] += n

    def answered(self) -> Pending:
        """The waiting frame is answered (a fill, or an error in its place): it becomes the last
        answered and the slot empties.  Returns it."""
        p = self.pending
        assert p is not None
        self.last_seq, self.pending = p.frame.seq, None
        return p

    def filled(self, degraded: bool) -> Pending:
        """The waiting frame's fill goes out (``degraded``: held or at a cheaper level)."""
        p = self.answered()
        self.filled_seq(p.frame.seq, degraded)
        return p

    def filled_seq(self, seq: int, degraded: bool) -> None:
        """:meth:`filled` for frame ``seq`` of a bundle served as arrays (daemon/blockpath.py),
        which never sat in the pending slot."""
        self.last_seq = seq
        self.late_streak = 0
        self.counts["frames_out"] += 1
        if degraded:
            self.counts["degraded"] += 1

    def gap_restart(self) -> None:
        """Too many frames missed for the filter to predict through: start it afresh."""
        self.restart()
        self.counts["restarts"] += 1

    def stepped(self, frame: np.ndarray, seq: int | None = None) -> None:
        """The filter took the waiting frame (or frame ``seq`` of a bundle served as arrays)
        and completed it to ``frame`` (model space)."""
        if seq is None:
            assert self.pending is not None
            seq = self.pending.frame.seq
        self.model_seq = seq
        self.last_out = np.asarray(frame, dtype=np.float64)
        self.held_streak = 0

    def held(self, out: np.ndarray, seq: int | None = None) -> None:
        """The waiting frame (or frame ``seq`` of a bundle served as arrays) is answered by
        hold-last-value (``out``); the filter skips it rather than predicting it later
        (replaying held frames when the stream steps again would cost the time the daemon is
        short of: a death spiral)."""
        if seq is None:
            assert self.pending is not None
            seq = self.pending.frame.seq
        self.last_out = out
        if self.model_seq is not None:
            self.model_seq = seq
        self.held_streak += 1
        self.counts["held"] += 1

    def to_model(self, f: wire.Frame) -> tuple[np.ndarray, np.ndarray]:
        """Studio frame -> model-space (frame, observed), float64 / bool, (n_model,) each."""
        mp = self.mapping
        a = f.angles.astype(np.float64)
        obs_in = np.isfinite(a) if f.observed is None else f.observed
        if mp.identity:
            return np.where(obs_in, a, np.nan), obs_in.copy()
        frame = np.full(mp.n_model, np.nan)
        obs = np.zeros(mp.n_model, bool)
        frame[mp.m_idx] = a[mp.s_idx]
        obs[mp.m_idx] = obs_in[mp.s_idx]
        frame[~obs] = np.nan
        return frame, obs

    def info(self) -> dict[str, Any]:
        d: dict[str, Any] = dict(self.counts)
        d.update(model=self.model_name, last_seq=self.last_seq, channels=self.mapping.n_in,
                 passthrough=len(self.mapping.passthrough), missing=len(self.mapping.missing),
                 idle_s=round(time.perf_counter() - self.last_active, 3), max_wait_ms=round(self.max_wait_s * 1e3, 1))
        d["dropped"] = sum(v for k, v in self.counts.items() if k.startswith("dropped_"))
        return d


def stepped_rows(sessions: list[Session], frames: np.ndarray, seqs: list[int]) -> None:
    """:meth:`Session.stepped` for each stream of a bundle served as arrays: ``frames`` (n, C)
    float64, a row each (daemon/tickblock.py; one loop, not n calls)."""
    for s, f, q in zip(sessions, frames, seqs):
        s.model_seq = q
        s.last_out = f
        s.held_streak = 0


def filled_rows(sessions: list[Session], seqs: list[int], degraded: list[bool] | None) -> None:
    """:meth:`Session.filled_seq` for each stream of a bundle served as arrays (None: none degraded)."""
    for i, (s, q) in enumerate(zip(sessions, seqs)):
        s.last_seq = q
        s.late_streak = 0
        c = s.counts
        c["frames_out"] += 1
        if degraded is not None and degraded[i]:
            c["degraded"] += 1


def _order(s: Session) -> int:
    return s.order


class SessionError(Exception):
    def __init__(self, reason: str, detail: str):
        self.reason, self.detail = reason, detail
        super().__init__(f"{reason}: {detail}")
