"""Decode -> session: a turn's messages taken from the transport's bytes to their sessions.

``Dispatch`` (a part of :class:`daemon.loop.Daemon`) turns each received message (bytes and the
origin it came from) into what it means: a frame handed to its session (which keeps the newest
per stream, see daemon/session.py), a hello, a bundle, a control request (daemon/control.py),
or a refusal.  It touches no socket: :meth:`Dispatch.dispatch` returns the answers (to whom,
what), and the loop hands them to the transport (daemon/loop.py).  Under a backlog, frames a newer frame of their
stream superseded within the burst are set aside undecoded, kept as what their answer needs
(daemon/aside.py), and answered after the fills (``superseded_answers``).
"""
from __future__ import annotations

from collections.abc import Generator
from typing import Any

from daemon import aside, blockpath, osc, oscblock, wire
from daemon import budget as budgets
from daemon.block import BlockBundle
from daemon.parts import Parts
from daemon.session import Origin, SessionError, principal

Answers = list[tuple[Origin, wire.Message]]  # (to whom, what): the loop hands them to the transport

OSC_ERRORS_PER_S = 20  # error answers a second to one OSC source host; the rest are counted, not sent
OSC_ERROR_FLOOR = 64  # bytes an OSC error answer may take even when what it answers was smaller (a reason code)
SLICE = 16  # messages of a barrier burst between two looks at the clock (see _batch)
BATCH_MIN = 3  # messages in a turn from which frames superseded within it are answered after the step
REJECT_LOG_PER_S = 20  # rejection log lines per second; the rest are counted, summarised


class Dispatch(Parts):
    """The ingest half of the daemon (mixed into :class:`daemon.loop.Daemon`)."""

    def _take_bytes(self, data: bytes, origin: Origin, arrived: float, counted: bool = False) -> None:
        if not counted:
            self.metrics.inc("messages_in")
        if origin[0] != "osc":
            if (bb := self._by_layout(data, origin)) is not None:
                return self._dispatch(bb, origin, arrived)
            try:
                m = wire.unpack(data, self.cfg.max_message_bytes)
            except wire.WireError as e:
                self._reject(origin, e.reason, e.detail, e.stream, e.seq)
                return
            self._handle_map(m, origin, arrived)
            if self.layouts.on and m.get("type") == "frames":
                self.layouts.learn(data, m, principal(origin))
        elif data.startswith(osc.BUNDLE_PREFIX):  # several messages of one instant
            self._osc_in, self._osc_errs = len(data), []
            try:  # (a bundle of frames: as arrays where it can, daemon/oscblock.py)
                if not oscblock.take(self, data, origin, arrived):
                    self._take(self._osc_bundle, data, origin, arrived)
            finally:
                errs, self._osc_errs = self._osc_errs, None
                if errs:
                    self._osc_summary(origin, errs)
        else:
            self._osc_in = len(data)
            self._take(osc.decode, data, origin, arrived)

    def _by_layout(self, data: bytes, origin: Origin) -> BlockBundle | None:
        """A bundle laid out as one its sender sent before, read without msgpack (daemon/layout.py); None: the usual way."""
        if not self.layouts.known or (blk := self.layouts.read(data, principal(origin), self.cfg.max_message_bytes)) is None:
            return None
        self.metrics.inc("bundles_by_layout")
        return BlockBundle(blk)

    def _handle_map(self, m: dict[str, Any] | wire.WireError | bytes | BlockBundle, origin: Origin, arrived: float) -> None:
        """:meth:`_take_bytes` for a message already unpacked by :meth:`dispatch` (or its unpack error;
        bytes: an OSC datagram, not unpacked), counted there."""
        if type(m) is bytes:
            self._take_bytes(m, origin, arrived, counted=True)
        elif type(m) is BlockBundle:  # (read through its layout by dispatch)
            self._dispatch(m, origin, arrived)
        elif isinstance(m, wire.WireError):
            self._reject(origin, m.reason, m.detail, m.stream, m.seq)
        elif type(m) is dict and m.get("type") == "hello" and (units := budgets.names_cost(m)) and \
                not self.budget.allow(principal(origin), self.clock(), units):
            # (before decoding: checking a hello's names is the cost the budget is for)
            self._rate_limited(origin, m)
        else:  # (_take's decode and dispatch, for a map: it decodes to one message)
            try:
                msg = wire.decode_map(m)  # type: ignore[arg-type]  # (a dict: bytes and errors went above)
            except wire.WireError as e:
                self._reject(origin, e.reason, e.detail, e.stream, e.seq)
                return
            except Exception as e:  # noqa: BLE001 - a decoder bug must cost one message, never the loop
                self._internal("decode", e, origin, None, None)
                return
            self._dispatch(msg, origin, arrived)

    def _rate_limited(self, origin: Origin, m: dict[str, Any] | None = None) -> None:
        sid = m.get("stream") if m is not None else None
        self._reject(origin, "rate_limited", f"over this peer's budget for hello/control requests "
                                             f"({budgets.RATE:g} cost units a second, bursts of {budgets.BURST:g}; "
                                             f"a hello costs 1 + channels/64, a control request {budgets.CONTROL_COST:g})",
                     sid if isinstance(sid, str) else None, None)

    def _osc_bundle(self, data: bytes, maxb: int) -> list[Any]:
        items = osc.decode_bundle(data, maxb)
        self.metrics.inc("osc_bundles_in")
        return items

    def _take(self, decode: Any, data: Any, origin: Origin, arrived: float) -> None:
        """``decode(data, max_message_bytes)`` (a message, or an OSC bundle's list of them) and
        dispatch; what cannot be decoded is answered with its error, and a malformed element of
        a bundle costs only itself."""
        try:
            got = decode(data, self.cfg.max_message_bytes)
        except wire.WireError as e:
            self._reject(origin, e.reason, e.detail, e.stream, e.seq)
            return
        except Exception as e:  # noqa: BLE001 - a decoder bug must cost one message, never the loop
            self._internal("decode", e, origin, None, None)
            return
        for m in got if type(got) is list else (got,):
            if isinstance(m, wire.WireError):
                self._reject(origin, m.reason, m.detail, m.stream, m.seq)
            else:
                self._dispatch(m, origin, arrived)

    def _internal(self, where: str, e: Exception, origin: Origin | None, sid: str | None, seq: int | None) -> None:
        self.metrics.inc("internal_errors")
        self.log("error", "internal_error", where=where, stream=sid, error=f"{type(e).__name__}: {e}"[:300])
        self._reject(origin, "internal", f"{type(e).__name__} while handling the message", sid, seq)

    def dispatch_few(self, items: list[tuple[bytes, Origin, float]]) -> Answers:
        """:meth:`dispatch` for a turn of fewer than BATCH_MIN messages (nothing is set aside,
        nothing to slice): each taken in order; returns the answers.  (No generator: a live
        stream's turn is most often one frame, and a generator costs a few microseconds.)"""
        for data, origin, arrived in items:
            self._take_bytes(data, origin, arrived)
        return self._take_out()

    def dispatch(self, items: list[tuple[bytes, Origin, float]]) -> Generator[Answers, None, Answers]:
        """A turn's messages (bytes, origin, receipt time), in arrival order, to their sessions.
        Sends nothing: it yields the answers so far each time the frames taken so far should be
        served before the rest (a slice of a long burst of costly requests, see below), and
        returns the rest of its answers.  The loop hands them to the transport.

        Under a backlog most of them are frames that a newer frame of the same stream in the
        same burst supersedes; only the newest is served.  Those superseded frames are set
        aside, each burst only unpacked, and handled after the turn's fills went out
        (:meth:`superseded_answers`), so the frames served do not wait for them.  Everything else is handled now, in order.

        The answers are exactly those of handling every message in order: a set-aside frame is
        decoded and checked later through the same session code, against the stream's state
        as it was before the burst, and nothing is set aside when the burst has a message that
        changes sessions (hello, control, bundle), for a stream that is new or has a frame
        waiting, or when the frame meant to supersede them is not taken (malformed, say): then
        they are handled at once, in order."""
        if len(items) < BATCH_MIN:
            return self.dispatch_few(items)
        self.metrics.inc("messages_in", len(items))
        maxb = self.cfg.max_message_bytes
        maps: list[dict[str, Any] | wire.WireError | bytes | BlockBundle] = []
        keys: list[tuple[str, int] | None] = []
        barrier = False
        for data, origin, _ in items:
            k = None
            if origin[0] == "osc":  # OSC is decoded on its own path, in order
                m: dict[str, Any] | wire.WireError | bytes | BlockBundle = data
                barrier = True
            elif (bb := self._by_layout(data, origin)) is not None:
                m, barrier = bb, True  # (a bundle: handled in order, as its map would be)
            else:
                try:
                    m = wire.unpack(data, maxb)
                except wire.WireError as e:
                    m = e
            if type(m) is dict:
                k = wire.frame_key(m)
                if k is None and m.get("type") != "frame":
                    barrier = True  # hello, control, bundle, ...: handled in order with everything else
            maps.append(m)
            keys.append(k)
        chains: dict[str, list[int]] = {}  # stream -> indices set aside, behind its newest frame
        if not barrier:
            sessions = self.sessions.sessions
            # only streams with an owner that is not about to lose them (a frame from anyone
            # else is then refused whatever came before it: a released stream's adoption and a
            # silent owner's takeover depend on the order, so those bursts go in order)
            fresh = self.clock() - self.sessions.idle_s / 2
            single: dict[str, Any] = {}  # unowned stream -> its one sender in the burst (False: several)
            for k, it in zip(keys, items):
                if k is not None and (s := sessions.get(k[0])) is not None and s.owner is None:
                    w = principal(it[1])
                    if single.setdefault(k[0], w) != w:
                        single[k[0]] = False
            newest: dict[str, int] = {}
            for i, k in enumerate(keys):
                if k is None:
                    continue
                sid, seq = k
                j = newest.get(sid)
                if j is None:
                    s = sessions.get(sid)
                    if s is not None and s.pending is None and s.last_active > fresh and \
                            (s.owner is not None or single.get(sid) is not False):
                        newest[sid] = i
                elif seq > keys[j][1]:  # type: ignore[index]
                    chains.setdefault(sid, []).append(j)
                    newest[sid] = i
                else:  # not newer than the newest so far: answered late/duplicate with the chain
                    chains.setdefault(sid, []).append(i)
            heads = {newest[sid]: sid for sid in chains}
            skip = {i for c in chains.values() for i in c}
        else:
            heads, skip = {}, set()
        # a burst of costly requests (hellos, controls: that is what makes it a barrier) must not
        # hold up the frames read with it: every SLICE messages, once a quarter of the budget is
        # spent, the frames taken so far are served (as if the rest had come in the next turn)
        slice_at, t_slice = (SLICE if barrier else len(maps) + 1), self.clock()
        frames_seen = self.metrics.counters.get("frames_in", 0)
        for i, (m, (_, origin, arrived)) in enumerate(zip(maps, items)):
            if i in skip:
                continue
            if i and not i % slice_at and self.clock() - t_slice > self.sched.budget_s / 4:
                if self.metrics.counters.get("frames_in", 0) != frames_seen:
                    yield self._take_out()  # (the loop serves the frames taken so far)
                    frames_seen = self.metrics.counters.get("frames_in", 0)
                t_slice = self.clock()
            self._handle_map(m, origin, arrived)
            head = heads.get(i)
            if head is None:
                continue
            sid = head
            order = sorted(chains[sid] + [i])  # the stream's frames of the burst, in arrival order
            s = self.sessions.sessions[sid]
            p = s.pending
            if p is not None and p.frame.seq == keys[i][1]:  # type: ignore[index]
                # with None where the served frame came
                # (kept as heads, see daemon/aside.py: not decoded again when answered)
                self._superseded.append((s, s.last_seq, p, aside.chain_of(maps, items, order, i, s, principal)))
            else:  # the newest frame was refused and changed nothing: the rest count as usual
                for d in order:
                    if d != i:
                        self._handle_map(maps[d], items[d][1], items[d][2])
        return self._take_out()

    def _take_out(self) -> Answers:
        out, self._out = self._out, []
        return out

    def _frame_answers(self, out: Answers) -> None:
        """A session's immediate answers to a frame: a ``conflated`` drop (of the frame it
        replaced) waits for the turn's fills (:meth:`superseded_answers`), the rest go now."""
        for o, m in out:
            if type(m) is wire.Drop and m.reason == "conflated":
                self._conflated.append((o, m))
            else:
                self._out.append((o, m))

    def superseded_answers(self) -> Answers:
        """After the turn's fills: the ``conflated`` and ``overdue`` drops of the turn, and the
        answers to the frames :meth:`dispatch` set aside, each taken by its session (a kept head
        without decoding it, daemon/aside.py; anything else decoded)
        as it would have been in arrival order (``SessionTable.replay``), so it gets the answer
        it would have had then (``drop`` conflated, late or duplicate, or an ``error``)."""
        out, self._conflated = self._conflated, []
        todo, self._superseded = self._superseded, []
        for s, last_seq, served, chain in todo:
            self.sessions.replay(s, last_seq, served, chain, self._take_aside, self._frame_answers)
        out += self._take_out()
        out += self._conflated
        self._conflated = []
        return out

    def _take_aside(self, s: Any, item: Any) -> None:
        """An item of a chain :meth:`dispatch` set aside for ``s`` (daemon/aside.py), taken in the
        replay: a run of kept heads straight into the session (as :meth:`_dispatch` of each would,
        minus the decode and the checks they passed when kept), a map decoded and dispatched."""
        if type(item) is not list:
            self._handle_map(*item)
            return
        who = principal(item[0][2])
        if s.owner != who and who is not None:  # (not within one turn: the owner is the one they were kept for)
            for seq, t, origin, arrived in item:
                self._dispatch(wire.Frame(s.sid, seq, t, aside.missing(s.mapping.n_in)), origin, arrived)
            return
        self.metrics.inc("frames_in", len(item))
        sessions = self.sessions
        if sessions.blocks:
            sessions.materialize()
        try:
            if out := sessions.take_run(s, item):
                self._frame_answers(out)
        except Exception as e:  # noqa: BLE001 - a bug must cost these messages, never the loop
            for seq, _, origin, _ in item:
                self._internal("handle", e, origin, s.sid, seq)

    def _dispatch(self, msg: Any, origin: Origin, arrived: float) -> None:
        try:
            if isinstance(msg, wire.Frame):
                self.metrics.inc("frames_in")
                if out := self.sessions.frame(msg, origin, arrived, principal(origin)):
                    self._frame_answers(out)
            elif isinstance(msg, wire.Bundle):
                self._bundle(msg, origin, arrived)
            elif isinstance(msg, (wire.Hello, wire.Control)) and \
                    not self.budget.allow(principal(origin), self.clock(), budgets.HELLO_COST if isinstance(msg, wire.Hello)
                                          else budgets.CONTROL_COST):
                self._rate_limited(origin)
            elif isinstance(msg, wire.Hello):
                ack, orphans = self.sessions.hello(msg, principal(origin))
                for o, m in orphans:
                    self._out.append((o, m))
                self.log("info", "stream_hello", stream=msg.stream, model=ack.model, channels=len(ack.channels),
                         passthrough=len(ack.passthrough), missing=len(ack.missing))
                self._out.append((origin, ack))
            elif isinstance(msg, wire.Control):
                self._control(msg, origin)
            else:
                self._reject(origin, "unknown_type", f"{type(msg).__name__} is an answer, not a request", None, None)
        except SessionError as e:
            self._reject(origin, e.reason, e.detail, getattr(msg, "stream", None), getattr(msg, "seq", None))
        except Exception as e:  # noqa: BLE001 - a bug must cost one message, never the loop
            self._internal("handle", e, origin, getattr(msg, "stream", None), getattr(msg, "seq", None))

    def _bundle(self, msg: wire.Bundle, origin: Origin, arrived: float) -> None:
        """Each frame of a bundle as if it had come alone, at the bundle's arrival; over ROUTER
        their answers are marked to go back together (a third origin element, see Transports)."""
        self.metrics.inc("bundles_in")
        who = principal(origin)
        if origin[0] == "router":
            origin = (*origin, "bundle")
        # the usual bundle: its frames taken as one block, served as arrays (daemon/blockpath.py);
        # from PULL/SUB too (their fills go to PUB one by one, as the row path sends them)
        if origin[0] != "osc" and msg.block is not None and \
                (drops := blockpath.take(self.sessions, msg.block, origin, arrived, who)) is not None:
            self.metrics.inc("frames_in", len(msg.block))
            self._conflated += drops  # (a waiting bundle's frames it superseded: after the fills)
            return
        for f in msg.items:
            if isinstance(f, wire.WireError):
                self._reject(origin, f.reason, f.detail, f.stream, f.seq)
                continue
            self.metrics.inc("frames_in")
            try:
                self._frame_answers(self.sessions.frame(f, origin, arrived, who))
            except SessionError as e:  # one frame's refusal is its own answer; the rest go on
                self._reject(origin, e.reason, e.detail, f.stream, f.seq)
            except Exception as e:  # noqa: BLE001 - the loop goes on
                self.metrics.inc("internal_errors")
                self.log("error", "internal_error", where="bundle", stream=f.stream, error=f"{type(e).__name__}: {e}"[:300])
                self._reject(origin, "internal", f"{type(e).__name__} while handling the frame", f.stream, f.seq)

    def _reject(self, origin: Origin | None, reason: str, detail: str, sid: str | None, seq: int | None) -> None:
        self.metrics.reject(reason)
        s = self.sessions.sessions.get(sid) if sid else None
        if s is not None and reason != "not_owner":  # (someone else's message: counted `foreign` on the stream)
            s.count("rejected")
        # a flood of bad input must not turn into a flood of log lines: at most REJECT_LOG_PER_S
        # a second are written, the rest are summed into one line per housekeeping tick
        now = self.clock()
        if now - self._rej_window >= 1.0:
            self._rej_window, self._rej_logged = now, 0
        if self._rej_logged < REJECT_LOG_PER_S:
            self._rej_logged += 1
            self.log("warning", "rejected", reason=reason, detail=detail[:300], stream=sid, seq=seq,
                     transport=origin[0] if origin else None)
        else:
            self._rej_suppressed += 1
        if origin is None:
            return
        if origin[0] == "osc":
            if self._osc_errs is not None:  # an element of a bundle: one answer for them all, after it
                self._osc_errs.append((reason, detail))
            else:
                self._osc_error(origin, wire.ErrorMsg(reason, detail, sid, seq))
            return
        self._out.append((origin, wire.ErrorMsg(reason, detail, sid, seq)))

    # ---- OSC error answers: bounded (no amplification, no reflection flood) ---------------
    def _osc_summary(self, origin: Origin, errs: list[tuple[str, str]]) -> None:
        by: dict[str, int] = {}
        for r, _ in errs:
            by[r] = by.get(r, 0) + 1
        counts = ", ".join(f"{r} x{n}" for r, n in sorted(by.items(), key=lambda kv: -kv[1]))
        self._osc_error(origin, wire.ErrorMsg(errs[0][0], f"{len(errs)} message(s) of the bundle refused ({counts}); "
                                                         f"first: {errs[0][1]}"))

    def _osc_error(self, origin: Origin, msg: wire.ErrorMsg) -> None:
        """An OSC error answer, at most OSC_ERRORS_PER_S a second per source host and no larger
        than the datagram it answers or OSC_ERROR_FLOOR bytes, whichever is more (the detail
        is cut to fit; an answer that cannot fit is not sent): spoofing a source cannot turn
        the daemon into an amplifier."""
        if not self.osc_err_budget.allow(origin[1][0], self.clock()):
            self.metrics.inc("osc_errors_unanswered")
            return
        room = max(self._osc_in, OSC_ERROR_FLOOR)
        data = osc.encode(msg)
        if len(data) > room:
            base = len(osc.encode(wire.ErrorMsg(msg.reason, "")))
            keep = room - base - 4  # (the detail's terminator and padding)
            if keep < 0:
                self.metrics.inc("osc_errors_unanswered")
                return
            msg = wire.ErrorMsg(msg.reason, msg.detail.encode()[:keep].decode(errors="ignore"), msg.stream, msg.seq)
        self._out.append((origin, msg))
