"""Seeded generator of malformed messages for both daemon transports (msgpack over ZeroMQ, OSC
over UDP).

Every generator returns ``(payload bytes, category)``.  The categories follow issue 7's list:
bytes that are not msgpack/OSC, wrong types, missing fields, wrong or huge array lengths,
NaN/inf in observed values, absurd sequence numbers and timestamps, unknown schema versions,
oversize messages.  Malformed here means *rejected by the decoder*: :meth:`Fuzz.zmq_batch` and
:meth:`Fuzz.osc_batch` keep only payloads that the daemon's own decoders refuse (a random byte
flip can leave a message valid; such a payload is drawn again), and return the reason each one
is expected to be counted under, so a test can compare the daemon's per-reason counters with
what it sent.  Session-level refusals (frame width, unknown model, the cap on streams) need
well-formed messages and a known session table; :func:`new_stream_frames` and friends build those.

Deterministic for a given seed: ``Fuzz(seed).zmq_batch(n)`` is the same list on every run.
"""
from __future__ import annotations

import math
import random
import struct
from collections.abc import Callable

import msgpack
import numpy as np

from daemon import osc, wire

F32 = "<f4"


# ---- raw OSC encoding (our own, so it can also write what python-osc would refuse) -------------
def osc_str(s: str | bytes) -> bytes:
    b = s.encode() if isinstance(s, str) else s
    return b + b"\0" * (4 - len(b) % 4)


def osc_blob(b: bytes) -> bytes:
    return struct.pack(">i", len(b)) + b + b"\0" * (-len(b) % 4)


def osc_message(address: str | bytes, args: list[tuple[str, object]]) -> bytes:
    """args: (tag, value) with tag in i h f d s b T F N, written big-endian as OSC 1.0 says."""
    tags = "," + "".join(t for t, _ in args)
    out = [osc_str(address), osc_str(tags)]
    for t, v in args:
        if t == "i":
            out.append(struct.pack(">i", v))
        elif t == "h":
            out.append(struct.pack(">q", v))
        elif t == "f":
            out.append(struct.pack(">f", v))
        elif t == "d":
            out.append(struct.pack(">d", v))
        elif t == "s":
            out.append(osc_str(v))  # type: ignore[arg-type]
        elif t == "b":
            out.append(osc_blob(v))  # type: ignore[arg-type]
    return b"".join(out)


def osc_frame(sid: str, seq: int, t: float, values) -> bytes:
    return osc_message("/lacuna/frame", [("s", sid), ("i", seq), ("d", t)] + [("f", float(v)) for v in values])


def pack(d: object) -> bytes:
    return msgpack.packb(d, use_bin_type=True)


# ---- expected outcome, from the daemon's own decoders ------------------------------------------
ANSWER_TYPES = (wire.FillMsg, wire.HelloAck, wire.Drop, wire.ControlReply, wire.ErrorMsg)


def zmq_reason(data: bytes, max_bytes: int) -> tuple[str, str | None] | None:
    """(reason, stream id named) the daemon counts for this msgpack payload, or None if it
    would accept it.  The stream id is the one the rejection is charged to."""
    try:
        m = wire.decode(data, max_bytes)
    except wire.WireError as e:
        return e.reason, e.stream
    if isinstance(m, ANSWER_TYPES):
        return "unknown_type", None  # an answer sent as a request
    return None


def osc_reason(data: bytes, max_bytes: int) -> tuple[str, str | None] | None:
    """Why the daemon refuses this datagram (reason, stream charged), or None when it is not a
    single refusal (a bundle that is read is answered element by element)."""
    try:
        if data.startswith(osc.BUNDLE_PREFIX):
            items = osc.decode_bundle(data, max_bytes)
            if len(items) == 1 and isinstance(items[0], wire.WireError):
                return items[0].reason, items[0].stream
            return None
        osc.decode(data, max_bytes)
    except wire.WireError as e:
        return e.reason, e.stream
    return None


# ---- the generator --------------------------------------------------------------------------------
class Fuzz:
    """Malformed messages for a daemon with ``max_bytes`` = its max_message_bytes and streams of
    ``n_channels`` channels.  ``streams`` are ids the malformed messages may name (they are
    rejected before any session sees them, so naming a live stream is part of the test)."""

    def __init__(self, seed: int, n_channels: int, max_bytes: int, streams: list[str] | None = None):
        self.r = random.Random(seed)
        self.np = np.random.default_rng(seed)
        self.C = n_channels
        self.max_bytes = max_bytes
        self.streams = streams or ["fz"]

    # -- helpers
    def _bytes(self, n: int) -> bytes:
        return self.np.integers(0, 256, n, dtype=np.uint8).tobytes()

    def _sid(self) -> str:
        return self.r.choice(self.streams)

    def _angles(self, n: int | None = None) -> np.ndarray:
        return self.np.uniform(-180, 180, n or self.C).astype(np.float32)

    def _frame_map(self) -> dict:
        return {"v": 1, "type": "frame", "stream": self._sid(), "seq": self.r.randrange(1 << 20),
                "t": self.r.uniform(0, 1e4), "angles": self._angles().tobytes()}

    def _valid_zmq(self) -> bytes:
        k = self.r.random()
        if k < 0.6:
            return pack(self._frame_map())
        if k < 0.8:
            return pack({"v": 1, "type": "hello", "stream": self._sid(),
                         "channels": [f"c{i}" for i in range(self.C)], "model": "m"})
        return pack({"v": 1, "type": "control", "cmd": "status"})

    # -- msgpack categories: each returns one candidate payload
    def not_msgpack(self) -> bytes:
        k = self.r.random()
        if k < 0.4:
            return self._bytes(self.r.randrange(0, 200))
        if k < 0.6:  # reserved byte 0xc1, or a header promising more than follows
            return self.r.choice([b"\xc1", b"\xdf\xff\xff\xff\xff", b"\xdd\x7f\xff\xff\xff", b"\xdb\xff\xff\xff\xf0abc",
                                  b"\xc6\x7f\xff\xff\xff", b"\x91" * 5000, b"\xd9\x20short"])
        if k < 0.75:  # ext types (timestamps included) are refused
            return pack({"v": 1, "type": "frame", "stream": "x", "t": msgpack.ExtType(self.r.randrange(0, 127), b"abc")})
        if k < 0.9:  # valid map with trailing garbage
            return self._valid_zmq() + self._bytes(self.r.randrange(1, 8))
        return self._valid_zmq()[: self.r.randrange(1, 20)]  # truncated

    def not_a_map(self) -> bytes:
        return pack(self.r.choice([None, True, 7, -3, 1.5, "frame", b"\x00\x01", [1, 2, 3], [{"v": 1}]]))

    def bad_version(self) -> bytes:
        m = self._frame_map()
        v = self.r.choice([None, 0, 2, 99, -1, "1", True, [1], 1 << 40, "v1"])
        if v is None:
            del m["v"]
        else:
            m["v"] = v
        return pack(m)

    def unknown_type(self) -> bytes:
        m = self._frame_map()
        m["type"] = self.r.choice([None, "", "frames", "FRAME", 3, ["frame"], "hello-ack2", "x" * 500])
        if m["type"] is None:
            del m["type"]
        if self.r.random() < 0.3:  # an answer sent to the daemon as if it were a request
            return wire.encode(wire.Drop(self._sid(), 3, "late")) if self.r.random() < 0.5 else \
                wire.encode(wire.FillMsg(self._sid(), 1, 0.0, self._angles(), np.zeros(self.C, bool),
                                         np.zeros(self.C, np.float32), "ok", "m", 5))
        return pack(m)

    def missing_field(self) -> bytes:
        if self.r.random() < 0.2:
            return pack({"v": 1, "type": "hello", "stream": self._sid()})
        if self.r.random() < 0.2:
            return pack({"v": 1, "type": "control"})
        m = self._frame_map()
        del m[self.r.choice(["stream", "seq", "t", "angles"])]
        return pack(m)

    def wrong_type(self) -> bytes:
        m = self._frame_map()
        key = self.r.choice(["stream", "seq", "t", "angles", "observed", "hello.channels", "hello.model", "cmd"])
        if key == "hello.channels":
            return pack({"v": 1, "type": "hello", "stream": self._sid(),
                         "channels": self.r.choice(["lfemur.rx", 5, {"a": 1}, [1, 2], ["a", None], [b"bytes"]])})
        if key == "hello.model":
            return pack({"v": 1, "type": "hello", "stream": self._sid(), "channels": ["a"], "model": 5})
        if key == "cmd":
            return pack({"v": 1, "type": "control", "cmd": self.r.choice([5, None, ["status"], b"status"])})
        bad = {"stream": [5, 1.5, b"s1", ["s"], None, True],
               "seq": [1.0, "7", b"\x07", None, True, [7], 2.5],
               "t": ["now", None, b"1.5", [1.5], True],
               "angles": [[1.0, 2.0], "1,2,3", 5, None, {"a": 1.0}],
               "observed": [[1, 0], "101", 7, True]}[key]
        m[key] = self.r.choice(bad)
        return pack(m)

    def bad_length(self) -> bytes:
        m = self._frame_map()
        k = self.r.random()
        if k < 0.3:
            m["angles"] = self._bytes(4 * self.r.randrange(1, self.C + 1) + self.r.choice([1, 2, 3]))
        elif k < 0.45:
            m["angles"] = b""
        elif k < 0.6:  # more channels than any stream may have (MAX_CHANNELS)
            m["angles"] = b"\0" * 4 * (wire.MAX_CHANNELS + self.r.randrange(1, 64))
        elif k < 0.8:
            m["observed"] = b"\x01" * (self.C + self.r.choice([-1, 1, 5, -self.C + 1]))
        elif k < 0.9:
            return pack({"v": 1, "type": "hello", "stream": self._sid(), "channels": []})
        else:
            return pack({"v": 1, "type": "hello", "stream": self._sid(),
                         "channels": [f"c{i}" for i in range(wire.MAX_CHANNELS + 1)]})
        return pack(m)

    def non_finite(self) -> bytes:
        m = self._frame_map()
        a = self._angles()
        i = self.r.randrange(self.C)
        if self.r.random() < 0.5:
            a[i] = self.r.choice([np.inf, -np.inf])  # no mask: NaN means missing, inf is an error
        else:
            a[i] = self.r.choice([np.nan, np.inf, -np.inf])  # masked observed value that is not finite
            obs = np.ones(self.C, np.uint8)
            m["observed"] = obs.tobytes()
        m["angles"] = a.tobytes()
        return pack(m)

    def bad_timestamp(self) -> bytes:
        m = self._frame_map()
        m["t"] = self.r.choice([math.nan, math.inf, -math.inf])
        return pack(m)

    def bad_seq(self) -> bytes:
        m = self._frame_map()
        m["seq"] = self.r.choice([-1, -(1 << 63), 1 << 63, (1 << 64) - 1, -7])
        return pack(m)

    def bad_stream(self) -> bytes:
        m = self._frame_map()
        m["stream"] = self.r.choice(["", "x" * (wire.MAX_STREAM_ID + 1), "a\x00b", "line\nbreak", "\x1b[31m", "x" * 5000])
        return pack(m)

    def bad_channels(self) -> bytes:
        return pack({"v": 1, "type": "hello", "stream": self._sid(), "channels": ["a", "b", "a"]})

    def bad_mask(self) -> bytes:
        m = self._frame_map()
        obs = np.ones(self.C, np.uint8)
        obs[self.r.randrange(self.C)] = self.r.randrange(2, 256)
        m["observed"] = obs.tobytes()
        return pack(m)

    def unknown_command(self) -> bytes:
        if self.r.random() < 0.5:
            return pack({"v": 1, "type": "control", "cmd": self.r.choice(["shutdown", "exec", "", "STATUS", "x" * 300])})
        return pack({"v": 1, "type": "control", "cmd": "reset"})  # reset without a stream

    def oversize(self) -> bytes:
        """Just over the cap (up to 4 KiB over): the daemon reads these and says too_large;
        the ZeroMQ-level limit far above the cap is tested separately."""
        n = self.max_bytes + self.r.randrange(1, 4096)
        if self.r.random() < 0.5:
            return self._bytes(n)
        m = self._frame_map()
        m["pad"] = b"\0" * n
        return pack(m)

    def flipped(self) -> bytes:
        b = bytearray(self._valid_zmq())
        for _ in range(self.r.randrange(1, 4)):
            b[self.r.randrange(len(b))] = self.r.randrange(256)
        return bytes(b)

    ZMQ_CATEGORIES = ("not_msgpack", "not_a_map", "bad_version", "unknown_type", "missing_field", "wrong_type",
                      "bad_length", "non_finite", "bad_timestamp", "bad_seq", "bad_stream", "bad_channels",
                      "bad_mask", "unknown_command", "oversize", "flipped")

    def zmq_batch(self, n: int, oversize_share: float = 0.01) -> list[tuple[bytes, str, str, str | None]]:
        """n payloads ``(bytes, category, expected reason, stream charged)``, all refused by wire.decode."""
        gens: list[Callable[[], bytes]] = [getattr(self, c) for c in self.ZMQ_CATEGORIES if c != "oversize"]
        out = []
        while len(out) < n:
            if self.r.random() < oversize_share:
                cat = "oversize"
                data = self.oversize()
            else:
                g = self.r.choice(gens)
                cat, data = g.__name__, g()
            why = zmq_reason(data, self.max_bytes)
            if why is not None:
                out.append((data, cat, *why))
        return out

    # -- OSC categories
    def osc_not_osc(self) -> bytes:
        k = self.r.random()
        if k < 0.5:
            b = self._bytes(self.r.randrange(1, 200))
            return b if not b.startswith(b"/") else b"x" + b
        if k < 0.7:  # a bundle whose element declares more bytes than it has: nothing in it is readable
            el = osc_frame("fz", 1, 0.0, self._angles())
            return b"#bundle\0" + b"\0" * 8 + (len(el) + 4 * self.r.randrange(1, 64)).to_bytes(4, "big") + el
        return b"/" + self._bytes(self.r.randrange(0, 120))  # an address, then garbage

    def osc_truncated(self) -> bytes:
        b = osc_frame(self._sid(), self.r.randrange(1 << 20), 0.5, self._angles())
        return b[: self.r.randrange(1, len(b) - 1)]

    def osc_wrong_tags(self) -> bytes:
        sid, a = self._sid(), self._angles()
        k = self.r.randrange(7)
        if k == 0:  # seq as a float
            return osc_message("/lacuna/frame", [("s", sid), ("f", 1.0), ("d", 0.0)] + [("f", v) for v in a])
        if k == 1:  # stream as an int
            return osc_message("/lacuna/frame", [("i", 5), ("i", 1), ("d", 0.0)] + [("f", v) for v in a])
        if k == 2:  # no angles
            return osc_message("/lacuna/frame", [("s", sid), ("i", 1), ("d", 0.0)])
        if k == 3:  # a string among the angles
            return osc_message("/lacuna/frame", [("s", sid), ("i", 1), ("d", 0.0), ("f", 1.0), ("s", "x")])
        if k == 4:  # masked frame with floats instead of blobs
            return osc_message("/lacuna/frame/masked", [("s", sid), ("i", 1), ("d", 0.0), ("f", 1.0), ("f", 1.0)])
        if k == 5:  # hello with an int channel name
            return osc_message("/lacuna/hello", [("s", sid), ("s", ""), ("s", "a"), ("i", 3)])
        return osc_message("/lacuna/reset", [])

    def osc_non_finite(self) -> bytes:
        a = self._angles()
        a[self.r.randrange(self.C)] = self.r.choice([np.inf, -np.inf])
        if self.r.random() < 0.5:
            return osc_frame(self._sid(), 1, 0.0, a)
        return osc_message("/lacuna/frame", [("s", self._sid()), ("i", 1), ("d", self.r.choice([math.nan, math.inf]))]
                           + [("f", float(v)) for v in self._angles()])

    def osc_bad_lengths(self) -> bytes:
        sid = self._sid()
        k = self.r.randrange(4)
        if k == 0:
            return osc_message("/lacuna/frame/masked", [("s", sid), ("i", 1), ("d", 0.0),
                                                        ("b", self._bytes(4 * self.C + 2)), ("b", b"\x01" * self.C)])
        if k == 1:
            return osc_message("/lacuna/frame/masked", [("s", sid), ("i", 1), ("d", 0.0),
                                                        ("b", self._angles().tobytes()), ("b", b"\x01" * (self.C + 3))])
        if k == 2:  # mask byte that is not 0/1
            return osc_message("/lacuna/frame/masked", [("s", sid), ("i", 1), ("d", 0.0),
                                                        ("b", self._angles().tobytes()), ("b", b"\x07" * self.C)])
        return osc_message("/lacuna/hello", [("s", sid), ("s", "")])  # no channels

    def osc_bad_values(self) -> bytes:
        k = self.r.randrange(3)
        if k == 0:
            return osc_frame(self._sid(), -self.r.randrange(1, 1 << 31), 0.0, self._angles())
        if k == 1:
            return osc_frame(self.r.choice(["", "a\x01b", "x" * 300]), 1, 0.0, self._angles())
        return osc_message("/lacuna/hello", [("s", self._sid()), ("s", ""), ("s", "a"), ("s", "a")])

    def osc_unknown_address(self) -> bytes:
        addr = self.r.choice(["/lacuna/nope", "/lacuna", "/lacuna/frame/", "/LACUNA/FRAME", "/x", "/lacuna/fill",
                              "/lacuna/status"])
        return osc_message(addr, [("s", self._sid()), ("i", 1)])

    def osc_oversize(self) -> bytes:
        n = self.max_bytes + self.r.randrange(1, 2048)
        return osc_message("/lacuna/frame", [("s", self._sid()), ("i", 1), ("d", 0.0), ("b", b"\0" * n)])

    OSC_CATEGORIES = ("osc_not_osc", "osc_truncated", "osc_wrong_tags", "osc_non_finite", "osc_bad_lengths",
                      "osc_bad_values", "osc_unknown_address")

    def osc_batch(self, n: int, oversize_share: float = 0.01) -> list[tuple[bytes, str, str, str | None]]:
        """n datagrams ``(bytes, category, expected reason, stream charged)``, each refused whole by the daemon."""
        gens: list[Callable[[], bytes]] = [getattr(self, c) for c in self.OSC_CATEGORIES]
        out = []
        while len(out) < n:
            if self.r.random() < oversize_share:
                cat, data = "osc_oversize", self.osc_oversize()
            else:
                g = self.r.choice(gens)
                cat, data = g.__name__, g()
            why = osc_reason(data, self.max_bytes)
            if why is not None:
                out.append((data, cat, *why))
        return out


# ---- well-formed messages the session layer refuses -----------------------------------------------
def new_stream_frames(prefix: str, n: int, n_channels: int, osc_form: bool = False) -> list[bytes]:
    """First frames of ``n`` streams never seen before (refused with too_many_streams once the
    daemon's session table is full)."""
    a = np.zeros(n_channels, np.float32)
    if osc_form:
        return [osc_frame(f"{prefix}{i}", 0, 0.0, a) for i in range(n)]
    return [wire.encode(wire.Frame(f"{prefix}{i}", 0, 0.0, a)) for i in range(n)]


def wrong_width_frames(sid: str, n: int, n_channels: int, seed: int) -> list[bytes]:
    """Frames for an open stream of ``n_channels`` channels with another width (refused: width)."""
    r = random.Random(seed)
    out = []
    for i in range(n):
        w = r.choice([c for c in (1, n_channels - 1, n_channels + 1, 2 * n_channels) if c > 0 and c != n_channels])
        out.append(wire.encode(wire.Frame(sid, 10 + i, 0.0, np.zeros(w, np.float32))))
    return out
