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
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import islice
from typing import Any

import numpy as np

from daemon import positions, wire
from lacuna.filler import FillerState, Model

Origin = tuple  # (transport name, address): ("router", envelope) | ("router", envelope, "bundle") | ("pull", None) | ("osc", (host, port))
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


def principal(origin: Origin) -> tuple:
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

    @classmethod
    def build(cls, studio: list[str], model_channels: list[str]) -> Mapping:
        pos = {c: i for i, c in enumerate(model_channels)}
        s_idx = np.array([i for i, c in enumerate(studio) if c in pos], dtype=np.intp)
        m_idx = np.array([pos[c] for c in studio if c in pos], dtype=np.intp)
        sent = set(studio)
        return cls(list(studio), s_idx, m_idx, [c for c in studio if c not in pos],
                   [c for c in model_channels if c not in sent], len(model_channels))

    @property
    def n_in(self) -> int:
        return len(self.channels)

    @property
    def identity(self) -> bool:
        """The studio sends exactly the model's channels in the model's order (the usual case):
        frames need no reordering either way."""
        ident = self.__dict__.get("_identity")
        if ident is None:
            n = self.n_model
            ident = self.__dict__["_identity"] = bool(
                self.n_in == n and self.s_idx.size == n and (self.s_idx == np.arange(n)).all()
                and (self.m_idx == np.arange(n)).all())
        return ident


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


def _order(s: Session) -> int:
    return s.order


class SessionError(Exception):
    def __init__(self, reason: str, detail: str):
        self.reason, self.detail = reason, detail
        super().__init__(f"{reason}: {detail}")


class SessionTable:
    """All live sessions.  ``resolve(name)`` gives (model name, Model) for a requested model."""

    def __init__(self, resolve: Callable[[str | None, str], tuple[str, Model]], max_streams: int,
                 count: Callable[[str, str | None], None], clock: Callable[[], float] = time.perf_counter):
        self.clock = clock  # the daemon's clock: activity, ownership timeouts, idle expiry
        self.sessions: dict[str, Session] = {}
        # stream ids, least recently active first (a frame or hello moves one to the end): status
        # lists the most recent without looking at the idle ones, expiry stops at the first live one
        self.recent: OrderedDict[str, None] = OrderedDict()
        # sessions given a waiting frame since the daemon last served (it looks only at these;
        # ones whose frame went meanwhile, or that were replaced, it skips)
        self.waiting: dict[int, Session] = {}
        self._opened = 0  # streams opened so far: a session's `order` (the table's own order)
        self.resolve = resolve
        self.max_streams = max_streams
        self.count = count  # count(counter name, stream id or None): global metrics hook
        self.expired = 0
        self.idle_s = float("inf")  # an owner silent this long gives its stream up (the daemon sets idle_timeout_s)
        self.takeovers = 0  # streams taken over by a claim token or from a silent owner

    # ---- ownership --------------------------------------------------------------------------
    def _owned(self, s: Session, who: Any, claim: str | None = None) -> bool:
        """May ``who`` act on ``s``?  Taking it over (claim token, silent owner) says yes."""
        if who is None or s.owner is None or s.owner == who:
            return True
        if (claim is not None and claim == s.claim) or self.clock() - s.last_active > self.idle_s:
            self.takeovers += 1
            return True
        s.counts["foreign"] += 1
        return False

    @staticmethod
    def _foreign(sid: str, what: str) -> SessionError:
        return SessionError("not_owner", f"stream {sid!r} belongs to another connection; {what} refused (a stream is "
                                         f"free once its owner is silent for idle_timeout_s; a reconnecting owner "
                                         f"sends its hello with the stream's claim token)")

    # ---- lifecycle --------------------------------------------------------------------------
    def _resolve(self, model_req: str | None, sid: str) -> tuple[str, Model]:
        try:
            return self.resolve(model_req, sid)
        except KeyError as e:
            raise SessionError("unknown_model", str(e.args[0])) from None

    def _new(self, sid: str, studio: list[str] | None, model_req: str | None, width: int = 0) -> Session:
        if sid not in self.sessions and len(self.sessions) >= self.max_streams:
            raise SessionError("too_many_streams", f"{len(self.sessions)} streams are open, the limit is {self.max_streams}")
        name, model = self._resolve(model_req, sid)
        chans = list(model.channels)
        if not chans:  # pass-through "any channels": the studio's list (or the first frame's width) decides
            chans = studio if studio is not None else [f"ch{i}" for i in range(width)]
        if studio is None:
            studio = chans
        mp = Mapping.build(studio, chans)
        if chans and mp.s_idx.size == 0:
            raise SessionError("bad_channels", f"none of the {len(studio)} channels is a channel of model {name!r} "
                                               f"(got {studio[:3]}..., model has {chans[:3]}...)")
        s = Session(sid, name, model, mp, model.stream(), last_active=self.clock())
        old = self.sessions.get(sid)
        if old is not None:
            s.counts, s.order = old.counts, old.order
        else:
            self._opened += 1
            s.order = self._opened
        self.sessions[sid] = s
        self.recent[sid] = None
        self.recent.move_to_end(sid)
        return s

    def hello(self, msg: wire.Hello, who: Any = None) -> tuple[wire.HelloAck, Out]:
        """(ack, answers for a frame that was waiting under the old handshake)."""
        old = self.sessions.get(msg.stream)
        if old is not None and not self._owned(old, who, msg.claim):
            raise self._foreign(msg.stream, "hello")
        if msg.positions:  # checked before the session is made: a refused hello leaves the stream as it was
            name, model = self._resolve(msg.model, msg.stream)
            try:
                fk = positions.stream_fk(model, name, Mapping.build(msg.channels, list(model.channels)))
            except ValueError as e:
                raise SessionError(positions.NO_SKELETON, str(e)) from None
        s = self._new(msg.stream, msg.channels, msg.model)
        s.owner, s.claim = who, msg.claim
        mp = s.mapping
        ack = wire.HelloAck(msg.stream, s.model_name, mp.channels, mp.passthrough, mp.missing)
        if msg.positions:
            s.fk = fk
            ack.joints, ack.parents = fk.joints, fk.parents
        return ack, self._orphan(old)

    def reset(self, sid: str, who: Any = None, operator: bool = False) -> tuple[bool, Out]:
        """End stream ``sid``: its owner may, an operator may end anyone's."""
        old = self.sessions.get(sid)
        if old is not None and not operator and not self._owned(old, who):
            raise self._foreign(sid, "reset")
        self.sessions.pop(sid, None)
        self.recent.pop(sid, None)
        return old is not None, self._orphan(old)

    def release(self, sid: str, who: Any = None) -> bool:
        """The owner gives its stream up (a client closing): state and counters stay, and the
        next principal to send a frame or hello for it owns it."""
        s = self.sessions.get(sid)
        if s is None:
            return False
        if not self._owned(s, who):
            raise self._foreign(sid, "release")
        s.owner, s.claim = None, None
        return True

    def _orphan(self, old: Session | None) -> Out:
        """A frame still waiting in a session being replaced gets its answer: dropped, ``reset``."""
        if old is None or old.pending is None:
            return []
        p, old.pending = old.pending, None
        old.counts["dropped_reset"] += 1
        self.count("dropped_reset", old.sid)
        return [(p.origin, wire.Drop(old.sid, p.frame.seq, "reset"))]

    def expire(self, now: float, idle_s: float) -> list[str]:
        """End the streams idle for more than ``idle_s``: from the least recently active, up to
        the first that is not (cost: the streams expired, not the streams open)."""
        gone = []
        for sid in self.recent:
            s = self.sessions[sid]
            if now - s.last_active <= idle_s:
                break
            if s.pending is None:
                gone.append(sid)
        for sid in gone:
            del self.sessions[sid]
            del self.recent[sid]
        self.expired += len(gone)
        return gone

    def most_recent(self, n: int) -> list[str]:
        """The ``n`` most recently active stream ids, most recent first."""
        return list(islice(reversed(self.recent), n))

    def rebind(self, name: str, model: Model) -> int:
        """After a reload swapped model ``name``: its sessions get states of the new model.

        Sequence numbers and counters stay; the filter state restarts (a new model's state is
        not the old one's).  A stream whose channels no longer overlap keeps the old model.
        """
        n = 0
        for s in self.sessions.values():
            if s.model_name != name:
                continue
            chans = list(model.channels) or s.mapping.channels
            mp = Mapping.build(s.mapping.channels, chans)
            if chans and mp.s_idx.size == 0:
                continue
            if s.fk is not None:  # a stream that asked for positions keeps them, or keeps its old model
                try:
                    s.fk = positions.stream_fk(model, name, mp)
                except ValueError:
                    continue
            s.model, s.mapping, s.state = model, mp, model.stream()
            s.model_seq, s.last_out = None, None
            n += 1
        return n

    def conflate(self, s: Session) -> Out:
        """The frame waiting in ``s`` is superseded by a newer one that was served: ``conflated``."""
        if s.pending is None:
            return []
        p, s.pending = s.pending, None
        s.counts["dropped_conflated"] += 1
        self.count("dropped_conflated", s.sid)
        return [(p.origin, wire.Drop(s.sid, p.frame.seq, "conflated"))]

    def overdue(self, s: Session) -> Out:
        """The frame waiting in ``s`` cannot be answered within the budget: ``overdue``.  It
        counts as answered (a repeat of it is a duplicate).  The filter skips it, as it skips a
        held frame: predicting through it at the next frame would cost time the daemon is short
        of, making the next frame overdue too."""
        p, s.pending = s.pending, None
        assert p is not None
        s.last_seq = p.frame.seq
        s.late_streak += 1
        if s.model_seq is not None and s.model_seq < p.frame.seq:
            s.model_seq = p.frame.seq
        s.counts["dropped_overdue"] += 1
        self.count("dropped_overdue", s.sid)
        return [(p.origin, wire.Drop(s.sid, p.frame.seq, "overdue"))]

    # ---- frames -----------------------------------------------------------------------------
    def frame(self, f: wire.Frame, origin: Origin, arrived: float, who: Any = None) -> Out:
        """Take a frame into its session's pending slot; returns the immediate answers."""
        s = self.sessions.get(f.stream)
        out: Out = []
        if s is not None and s.owner != who and who is not None:
            if not self._owned(s, who):
                raise self._foreign(f.stream, "frame")
            if s.owner is not None:  # taken over from a silent owner: a fresh stream
                out = self._orphan(s)
                s = None
            else:  # released (or opened in-process): the sender adopts it
                s.owner = who
        if s is None:
            s = self._new(f.stream, None, None, f.angles.shape[0])
            s.owner = who
        if f.angles.shape[0] != s.mapping.n_in:
            raise SessionError("width", f"stream {f.stream!r} has {s.mapping.n_in} channels, the frame has "
                                        f"{f.angles.shape[0]} (send a hello to change the channel list)")
        s.last_active = self.clock()
        self.recent.move_to_end(f.stream)
        # did the frame wait on its way (a stalled daemon, a full socket)?  arrival - capture time
        # is constant for a frame delivered as quickly as ever; more means it waited
        off = arrived - f.t
        b = s.t_base
        if b is None or off < b:
            s.t_base = off
        else:
            w = off - b
            if w > WAIT_PLAUSIBLE_S:  # the capture clock jumped: a new baseline
                s.t_base = off
            else:
                s.t_base = b + w * WAIT_FOLLOW
                if w >= WAIT_REPORT_S:
                    s.counts["waited"] += 1
                    self.count("frames_waited", f.stream)
                    if w > s.max_wait_s:
                        s.max_wait_s = w
        s.counts["frames_in"] += 1
        if s.last_seq is not None and f.seq <= s.last_seq:
            why = "duplicate" if f.seq == s.last_seq else "late"
            s.counts[f"dropped_{why}"] += 1
            self.count(f"dropped_{why}", f.stream)
            return out + [(origin, wire.Drop(f.stream, f.seq, why))]
        p = s.pending
        if p is not None:
            if f.seq <= p.frame.seq:
                why = "duplicate" if f.seq == p.frame.seq else "late"
                s.counts[f"dropped_{why}"] += 1
                self.count(f"dropped_{why}", f.stream)
                return [(origin, wire.Drop(f.stream, f.seq, why))]
            s.counts["dropped_conflated"] += 1
            self.count("dropped_conflated", f.stream)
            out.append((p.origin, wire.Drop(f.stream, p.frame.seq, "conflated")))
        s.pending = Pending(f, origin, arrived)
        self.waiting[id(s)] = s
        return out

    def take_waiting(self) -> list[Session]:
        """The sessions with a frame waiting, in the table's order (as a walk over every open
        session would give them); empties the list."""
        w, self.waiting = self.waiting, {}
        live = self.sessions
        out = [s for s in w.values() if s.pending is not None and live.get(s.sid) is s]
        if len(out) > 1:
            out.sort(key=_order)
        return out
