"""The table of live sessions: opening (hello, a first frame), ownership, conflation into each
stream's pending slot, reset, release, idle expiry, and the replay of a burst's superseded
frames.  One session's own transitions are methods of :class:`daemon.session.Session`."""
from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable
from itertools import islice
from typing import Any

from daemon import positions, wire
from daemon.aside import NO_ANGLES as _NO_ANGLES
from daemon.session import (
    Mapping,
    Origin,
    Out,
    Pending,
    Session,
    SessionError,
    _order,
)
from lacuna.filler import Model

MAPPINGS_KEPT = 64  # distinct (studio, model) channel lists whose Mapping is kept for the next hello


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
        # a regular bundle's frames waiting as one block (daemon/blockpath.py), and the checks of
        # its streams, valid while `gen` (bumped by every change of a session's identity, owner,
        # model or mapping) is unchanged
        self.blocks: list[Any] = []
        self.block_plans: dict[tuple[str, ...], Any] = {}
        self.gen = 0
        self.block_path = True  # (False: every bundle frame by frame; tests compare the two)
        self.block_served = 0  # bundles served as arrays
        self.block_overdue = 0  # of them, bundles with frames dropped overdue before the step
        # (studio channels, model channels) -> their Mapping, shared (a mapping is never changed):
        # performers of one studio send the same list, and building one is most of a hello's cost
        self._maps: dict[tuple[tuple[str, ...], tuple[str, ...]], Mapping] = {}

    def materialize(self) -> None:
        """The blocks waiting become the pending slots they stand for (before anything that
        reads or changes a session's pending slot: then the row path goes on as if it had
        taken those frames one by one)."""
        if self.blocks:
            blocks, self.blocks = self.blocks, []
            for bw in blocks:
                bw.to_pending(self.waiting)

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
        self.materialize()
        self.gen += 1
        if sid not in self.sessions and len(self.sessions) >= self.max_streams:
            raise SessionError("too_many_streams", f"{len(self.sessions)} streams are open, the limit is {self.max_streams}")
        name, model = self._resolve(model_req, sid)
        chans = list(model.channels)
        if not chans:  # pass-through "any channels": the studio's list (or the first frame's width) decides
            chans = studio if studio is not None else [f"ch{i}" for i in range(width)]
        if studio is None:
            studio = chans
        mp = self._mapping(studio, chans)
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

    def _mapping(self, studio: list[str], chans: list[str]) -> Mapping:
        key = (tuple(studio), tuple(chans))
        mp = self._maps.get(key)
        if mp is None:
            if len(self._maps) >= MAPPINGS_KEPT:
                self._maps.clear()
            mp = self._maps[key] = Mapping.build(studio, chans)
        return mp

    def hello(self, msg: wire.Hello, who: Any = None) -> tuple[wire.HelloAck, Out]:
        """(ack, answers for a frame that was waiting under the old handshake)."""
        self.materialize()
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
        self.materialize()
        self.gen += 1
        old = self.sessions.get(sid)
        if old is not None and not operator and not self._owned(old, who):
            raise self._foreign(sid, "reset")
        self.sessions.pop(sid, None)
        self.recent.pop(sid, None)
        return old is not None, self._orphan(old)

    def release(self, sid: str, who: Any = None) -> bool:
        """The owner gives its stream up (a client closing): state and counters stay, and the
        next principal to send a frame or hello for it owns it."""
        self.gen += 1
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
        self.materialize()
        gone = []
        for sid in self.recent:
            s = self.sessions[sid]
            if now - s.last_active <= idle_s:
                break
            if s.pending is None:
                gone.append(sid)
        if gone:
            self.gen += 1
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
        self.materialize()
        self.gen += 1
        n = 0
        for s in self.sessions.values():
            if s.model_name != name:
                continue
            chans = list(model.channels) or s.mapping.channels
            mp = self._mapping(s.mapping.channels, chans)  # (a reload rebinds every stream in one turn)
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
        return self.overdue_seq(s, p.frame.seq, p.origin)

    def overdue_seq(self, s: Session, seq: int, origin: Origin) -> Out:
        """:meth:`overdue` for frame ``seq`` of a bundle served as arrays (daemon/blockpath.py)."""
        s.last_seq = seq
        s.late_streak += 1
        if s.model_seq is not None and s.model_seq < seq:
            s.model_seq = seq
        s.counts["dropped_overdue"] += 1
        self.count("dropped_overdue", s.sid)
        return [(origin, wire.Drop(s.sid, seq, "overdue"))]

    # ---- frames -----------------------------------------------------------------------------
    def frame(self, f: wire.Frame, origin: Origin, arrived: float, who: Any = None) -> Out:
        """Take a frame into its session's pending slot; returns the immediate answers."""
        if self.blocks:
            self.materialize()
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
                self.gen += 1
        if s is None:
            s = self._new(f.stream, None, None, f.angles.shape[0])
            s.owner = who
            self.gen += 1
        if f.angles.shape[0] != s.mapping.n_in:
            raise SessionError("width", f"stream {f.stream!r} has {s.mapping.n_in} channels, the frame has "
                                        f"{f.angles.shape[0]} (send a hello to change the channel list)")
        s.last_active = self.clock()
        self.recent.move_to_end(f.stream)
        if s.delivered(arrived - f.t):
            self.count("frames_waited", f.stream)
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

    def take_run(self, s: Session, run: list[tuple[int, float, Origin, float]]) -> Out:
        """What :meth:`frame` does with each frame of ``run`` in turn, in one loop: the same state
        after, the same answers in the same order.  ``run``: frames of ``s``'s owner and width set
        aside by daemon/dispatch.py, kept as (seq, capture time, origin, arrival) (daemon/aside.py)."""
        sid, counts, count = s.sid, s.counts, self.count
        out: Out = []
        p = s.pending
        last = s.last_seq
        top = p.frame.seq if p is not None else None  # (the waiting frame's seq)
        for seq, t, origin, arrived in run:
            if s.delivered(arrived - t):
                count("frames_waited", sid)
            if last is not None and seq <= last:
                why = "duplicate" if seq == last else "late"
            elif top is not None and seq <= top:
                why = "duplicate" if seq == top else "late"
            else:
                if p is not None:
                    counts["dropped_conflated"] += 1
                    count("dropped_conflated", sid)
                    out.append((p.origin, wire.Drop(sid, top, "conflated")))  # type: ignore[arg-type]
                p, top = Pending(wire.Frame(sid, seq, t, _NO_ANGLES), origin, arrived), seq
                continue
            counts[f"dropped_{why}"] += 1
            count(f"dropped_{why}", sid)
            out.append((origin, wire.Drop(sid, seq, why)))
        counts["frames_in"] += len(run)
        s.last_active = self.clock()
        self.recent.move_to_end(sid)
        if p is not s.pending:
            s.pending = p
            self.waiting[id(s)] = s
        return out

    def replay(self, s: Session, last_seq: int | None, served: Pending, chain: list[Any],
               take: Callable[..., None], answer: Callable[[Out], None]) -> None:
        """The frames of a burst that a newer frame of ``s`` superseded (set aside by
        daemon/dispatch.py, ``chain`` in arrival order, None where the served frame came), taken
        now, after the fills, as they would have been in arrival order: against the stream as it
        was before the burst (``last_seq``, no frame waiting), the served frame waiting from its
        place in the chain on.  ``take(s, item)`` takes an item (a run of kept heads, or a map to
        decode: daemon/aside.py);
        ``answer`` gets the ``conflated`` drop of the frame waiting when the served one came.
        The stream's state afterwards is what it was before the call."""
        # (the burst held no hello or reset, so the session is the same object; a SIGHUP swap
        # runs between turns and keeps it)
        assert self.sessions.get(s.sid) is s and s.pending is None
        now_seq, s.last_seq = s.last_seq, last_seq
        try:
            for item in chain:
                if item is None:  # where the served frame came: it supersedes the one waiting
                    answer(self.conflate(s))
                    s.pending = served  # (frames after it are late or duplicates against it)
                else:
                    take(s, item)
        finally:
            s.last_seq = now_seq
            s.pending = None

    def abandon(self) -> list[tuple[Origin, str, int]]:
        """Empty every pending slot (after a failed tick); returns what each held, to be
        answered with an error: (origin, stream id, seq)."""
        self.materialize()
        owed = []
        for s in self.sessions.values():
            p, s.pending = s.pending, None
            if p is not None:
                owed.append((p.origin, s.sid, p.frame.seq))
        return owed

    def take_waiting(self) -> list[Session]:
        """The sessions with a frame waiting, in the table's order (as a walk over every open
        session would give them); empties the list."""
        self.materialize()
        w, self.waiting = self.waiting, {}
        live = self.sessions
        out = [s for s in w.values() if s.pending is not None and live.get(s.sid) is s]
        if len(out) > 1:
            out.sort(key=_order)
        return out
