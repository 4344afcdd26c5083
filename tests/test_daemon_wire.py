"""Wire schema v1 on literal bytes (the examples of docs/PROTOCOL.md), no sockets."""
from __future__ import annotations

import msgpack
import numpy as np
import pytest

from daemon import wire as w

# Literal fixtures named by content; the same bytes are printed in docs/PROTOCOL.md.
FRAME_S1_SEQ7_T1_5_NAN_MIDDLE = bytes.fromhex(
    "86a17601a474797065a56672616d65a673747265616da27331a373657107a174cb3ff8000000000000"
    "a6616e676c6573c40c000020410000c07f000020c0"
)
FRAME_S1_SEQ7_MASK_101 = bytes.fromhex(
    "87a17601a474797065a56672616d65a673747265616da27331a373657107a174cb3ff8000000000000"
    "a6616e676c6573c40c0000204100000000000020c0a86f62736572766564c403010001"
)
HELLO_S1_THREE_CHANNELS_WALK = bytes.fromhex(
    "85a17601a474797065a568656c6c6fa673747265616da27331a86368616e6e656c7393a96c66656d75722e7278"
    "a96c66656d75722e7279ac73747564696f2e6578747261a56d6f64656ca477616c6b"
)
FILL_S1_SEQ7_CH1_3_25_STD_0_5 = bytes.fromhex(
    "8ba17601a474797065a466696c6ca673747265616da27331a373657107a174cb3ff8000000000000"
    "a6616e676c6573c40c0000204100005040000020c0a666696c6c6564c403000100a3737464c40c000000000000"
    "003f00000000a6737461747573a26f6ba56d6f64656ca477616c6ba770726f635f7573cd019c"
)
CONTROL_STATUS = bytes.fromhex("83a17601a474797065a7636f6e74726f6ca3636d64a6737461747573")


def test_protocol_example_frame_nan_means_missing():
    m = w.decode(FRAME_S1_SEQ7_T1_5_NAN_MIDDLE)
    assert isinstance(m, w.Frame)
    assert (m.stream, m.seq, m.t) == ("s1", 7, 1.5)
    assert m.angles[0] == 10.0 and np.isnan(m.angles[1]) and m.angles[2] == -2.5
    assert m.observed is None
    assert w.encode(m) == FRAME_S1_SEQ7_T1_5_NAN_MIDDLE


def test_protocol_example_frame_with_mask():
    m = w.decode(FRAME_S1_SEQ7_MASK_101)
    assert isinstance(m, w.Frame)
    assert m.observed.tolist() == [True, False, True]
    assert w.encode(m) == FRAME_S1_SEQ7_MASK_101


def test_protocol_example_hello():
    m = w.decode(HELLO_S1_THREE_CHANNELS_WALK)
    assert m == w.Hello("s1", ["lfemur.rx", "lfemur.ry", "studio.extra"], "walk")
    assert w.encode(m) == HELLO_S1_THREE_CHANNELS_WALK


def test_protocol_example_fill():
    m = w.decode(FILL_S1_SEQ7_CH1_3_25_STD_0_5)
    assert isinstance(m, w.FillMsg)
    assert m.angles.tolist() == [10.0, 3.25, -2.5]
    assert m.filled.tolist() == [False, True, False]
    assert m.std.tolist() == [0.0, 0.5, 0.0]
    assert (m.status, m.model, m.proc_us, m.gap, m.style, m.phase) == ("ok", "walk", 412, 0, None, None)
    assert w.encode(m) == FILL_S1_SEQ7_CH1_3_25_STD_0_5


def test_protocol_example_control_status():
    assert w.decode(CONTROL_STATUS) == w.Control("status")
    assert w.encode(w.Control("status")) == CONTROL_STATUS


def test_fill_with_style_phase_gap_round_trip():
    m = w.FillMsg("a", 3, 0.25, np.ones(2, np.float32), np.array([1, 0], bool), np.zeros(2, np.float32),
                  "degraded", "m", 5, style=np.array([0.75, 0.25], np.float32), phase=0.5, gap=2)
    back = w.decode(w.encode(m))
    assert back.style.tolist() == [0.75, 0.25] and back.phase == 0.5 and back.gap == 2
    assert back.status == "degraded"


@pytest.mark.parametrize("msg", [
    w.HelloAck("s", "walk", ["a", "b"], ["b"], ["c"]),
    w.Drop("s", 4, "late"),
    w.Control("reset", "s9"),
    w.ControlReply("status", True, {"uptime_s": 1.0, "streams": {}}),
    w.ControlReply("reload", False, {}, "bad file"),
    w.ErrorMsg("version", "schema version must be 1 (got 2)", "s", 3),
])
def test_other_messages_round_trip(msg):
    assert w.decode(w.encode(msg)) == msg


def _pack(d):
    return msgpack.packb(d, use_bin_type=True)


GOOD = {"v": 1, "type": "frame", "stream": "s1", "seq": 1, "t": 0.0, "angles": b"\0" * 8}

# (bytes, expected reason): every one must come out as a WireError with that code.
BAD_CASES = [
    (b"", "not_msgpack"),
    (b"\xc1", "not_msgpack"),
    (FRAME_S1_SEQ7_T1_5_NAN_MIDDLE + b"\x00", "not_msgpack"),  # trailing garbage
    (FRAME_S1_SEQ7_T1_5_NAN_MIDDLE[:-3], "not_msgpack"),  # truncated
    (b"hello world", "not_msgpack"),
    (_pack([1, 2, 3]), "not_a_map"),
    (_pack(7), "not_a_map"),
    (_pack({**GOOD, "v": 2}), "version"),
    (_pack({k: v for k, v in GOOD.items() if k != "v"}), "version"),
    (_pack({**GOOD, "v": True}), "version"),
    (_pack({**GOOD, "type": "frobnicate"}), "unknown_type"),
    (_pack({**GOOD, "type": 3}), "unknown_type"),
    (_pack({k: v for k, v in GOOD.items() if k != "seq"}), "missing_field"),
    (_pack({k: v for k, v in GOOD.items() if k != "angles"}), "missing_field"),
    (_pack({**GOOD, "seq": "1"}), "bad_type"),
    (_pack({**GOOD, "seq": True}), "bad_type"),
    (_pack({**GOOD, "seq": -1}), "bad_seq"),
    (_pack({**GOOD, "t": float("nan")}), "bad_timestamp"),
    (_pack({**GOOD, "t": "now"}), "bad_type"),
    (_pack({**GOOD, "angles": b"\0" * 7}), "bad_length"),
    (_pack({**GOOD, "angles": b""}), "bad_length"),
    (_pack({**GOOD, "angles": [1.0, 2.0]}), "bad_type"),
    (_pack({**GOOD, "angles": b"\0" * (4 * (w.MAX_CHANNELS + 1))}), "bad_length"),
    (_pack({**GOOD, "observed": b"\1"}), "bad_length"),
    (_pack({**GOOD, "observed": b"\1\2"}), "bad_mask"),
    (_pack({**GOOD, "angles": np.array([np.nan, 1], "<f4").tobytes(), "observed": b"\1\1"}), "non_finite"),
    (_pack({**GOOD, "angles": np.array([np.inf, 1], "<f4").tobytes()}), "non_finite"),
    (_pack({**GOOD, "stream": ""}), "bad_stream"),
    (_pack({**GOOD, "stream": "x" * 200}), "bad_stream"),
    (_pack({**GOOD, "stream": "a\nb"}), "bad_stream"),
    (_pack({"v": 1, "type": "hello", "stream": "s"}), "missing_field"),
    (_pack({"v": 1, "type": "hello", "stream": "s", "channels": []}), "bad_length"),
    (_pack({"v": 1, "type": "hello", "stream": "s", "channels": ["a", "a"]}), "bad_channels"),
    (_pack({"v": 1, "type": "hello", "stream": "s", "channels": ["a", 3]}), "bad_type"),
    (_pack({"v": 1, "type": "control", "cmd": "format-disk"}), "unknown_command"),
    (_pack({"v": 1, "type": "control", "cmd": "reset"}), "missing_field"),
    (b"\xdd\xff\xff\xff\xff", "not_msgpack"),  # array claiming 4 billion entries
    (b"\xc6\x7f\xff\xff\xff", "not_msgpack"),  # bin claiming 2 GiB
]


@pytest.mark.parametrize("data,reason", BAD_CASES, ids=[r for _, r in BAD_CASES])
def test_raises_on_bad_message(data, reason):
    with pytest.raises(w.WireError) as ei:
        w.decode(data)
    assert ei.value.reason == reason, ei.value.detail


def test_raises_on_oversize_before_unpacking():
    with pytest.raises(w.WireError) as ei:
        w.decode(b"\x00" * 101, max_bytes=100)
    assert ei.value.reason == "too_large" and "101 bytes" in ei.value.detail


def test_rejection_carries_stream_and_seq_when_readable():
    with pytest.raises(w.WireError) as ei:
        w.decode(_pack({**GOOD, "stream": "cam3", "seq": 41, "angles": b"\0" * 5}))
    assert (ei.value.stream, ei.value.seq) == ("cam3", 41)
    err = w.decode(w.encode(w.error_for(ei.value)))
    assert isinstance(err, w.ErrorMsg) and err.reason == "bad_length" and err.stream == "cam3"


def test_random_bytes_never_raise_anything_but_wire_error(rng):
    for _ in range(3000):
        n = int(rng.integers(0, 80))
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        try:
            w.decode(data)
        except w.WireError:
            pass
    # mutate a good frame byte by byte: each result is a message or a WireError, never a crash
    base = bytearray(FRAME_S1_SEQ7_MASK_101)
    for i in range(len(base)):
        for val in (0x00, 0xC1, 0xFF, base[i] ^ 0x01):
            b = bytearray(base)
            b[i] = val
            try:
                w.decode(bytes(b))
            except w.WireError:
                pass


def test_masked_frame_fast_path_equals_the_checked_path_and_rejects_the_same():
    """The hot path reads a frame with an explicit observed mask without the field-by-field
    checks; it must decode exactly what the checked path decodes and leave every bad mask to it."""
    from daemon.decode import _decode_frame_checked

    angles = np.array([1.0, np.nan, 3.0, 4.0], np.float32)
    good = {"v": 1, "type": "frame", "stream": "s", "seq": 3, "t": 0.5, "angles": angles.tobytes(),
            "observed": bytes([1, 0, 1, 0])}
    fast = w.decode(msgpack.packb(good, use_bin_type=True))
    slow = _decode_frame_checked(good)
    assert fast.observed.dtype == bool and fast.observed.tolist() == slow.observed.tolist() == [True, False, True, False]
    assert np.array_equal(fast.angles, slow.angles, equal_nan=True) and (fast.stream, fast.seq, fast.t) == ("s", 3, 0.5)
    for bad, reason in (({"observed": bytes([1, 2, 1, 0])}, "bad_mask"),
                        ({"observed": bytes([1, 1, 1])}, "bad_length"),
                        ({"observed": bytes([1, 1, 1, 0])}, "non_finite"),   # channel 1 is NaN but marked observed
                        ({"angles": np.array([np.inf, 1, 3, 4], np.float32).tobytes()}, "non_finite")):
        with pytest.raises(w.WireError) as ei:
            w.decode(msgpack.packb({**good, **bad}, use_bin_type=True))
        assert ei.value.reason == reason, bad
    # a value in a slot the mask calls missing is never read, whatever it is
    odd = w.decode(msgpack.packb({**good, "angles": np.array([1, np.inf, 3, 4], np.float32).tobytes()}, use_bin_type=True))
    assert odd.observed.tolist() == [True, False, True, False]


def test_masked_fast_path_finiteness_agrees_with_the_checked_path_on_random_frames(rng):
    """The fast path decides "every observed value is finite" by CPython's double sum of those
    values (daemon/decode.py, bench/finite_cold.py); the checked path tests each value.  On frames
    with NaN, +-inf and float32's extremes scattered at random under random masks, both must
    accept and reject the same frames, and the fast path must hand back the same arrays."""
    from daemon.decode import _decode_frame_checked, well_formed

    specials = np.array([np.nan, np.inf, -np.inf, np.finfo(np.float32).max, -np.finfo(np.float32).max,
                         np.finfo(np.float32).tiny, 0.0, -0.0], np.float32)
    accepted = rejected = 0
    for _ in range(400):
        c = int(rng.integers(1, 80))
        angles = rng.normal(0, 90, c).astype(np.float32)
        k = int(rng.integers(0, min(c, 6) + 1))
        angles[rng.choice(c, k, replace=False)] = rng.choice(specials, k)
        observed = rng.random(c) < rng.random()
        m = {"v": 1, "type": "frame", "stream": "s", "seq": 1, "t": 0.0, "angles": angles.tobytes(),
             "observed": observed.astype(np.uint8).tobytes()}
        fast = well_formed(m)
        try:
            slow = _decode_frame_checked(m)
        except w.WireError as e:
            assert e.reason == "non_finite" and fast is None, (angles, observed)
            rejected += 1
            continue
        assert fast is not None and fast[4].tolist() == slow.observed.tolist() == observed.tolist()
        assert np.array_equal(fast[3], slow.angles, equal_nan=True)
        accepted += 1
    assert accepted > 50 and rejected > 50  # (both branches were exercised)


# ---- bundles ------------------------------------------------------------------------------------
FRAMES_S1_S2_SEQ7 = bytes.fromhex(  # docs/PROTOCOL.md, `frames`
    "83a17601a474797065a66672616d6573a66672616d65739284a673747265616da27331a373657107a174cb3ff8000000"
    "000000a6616e676c6573c40c000020410000c07f000020c085a673747265616da27332a373657107a174cb3ff8000000"
    "000000a6616e676c6573c40c00008040000000000000803fa86f62736572766564c403010001"
)
REPLIES_DROP_S2_SEQ7_LATE = bytes.fromhex(  # docs/PROTOCOL.md, `replies`
    "83a17601a474797065a77265706c696573a77265706c6965739185a17601a474797065a464726f70a673747265616da2"
    "7332a373657107a6726561736f6ea46c617465"
)


def test_protocol_example_bundle_and_replies():
    b = w.decode(FRAMES_S1_S2_SEQ7)
    assert isinstance(b, w.Bundle) and len(b.items) == 2
    f1, f2 = b.items
    assert (f1.stream, f1.seq, f1.t, f1.observed) == ("s1", 7, 1.5, None) and np.isnan(f1.angles[1])
    assert f2.stream == "s2" and f2.angles.tolist() == [4.0, 0.0, 1.0] and f2.observed.tolist() == [True, False, True]
    assert w.encode(b) == FRAMES_S1_S2_SEQ7
    r = w.decode(REPLIES_DROP_S2_SEQ7_LATE)
    assert r == w.Replies([w.Drop("s2", 7, "late")])
    assert w.encode(r) == REPLIES_DROP_S2_SEQ7_LATE == w.join_replies([w.encode(w.Drop("s2", 7, "late"))])


def test_bundle_elements_are_read_one_by_one_and_a_bad_one_costs_only_itself():
    good = {k: v for k, v in GOOD.items() if k not in ("v", "type")}
    items = [good, 7, {**good, "type": "hello"}, {**good, "v": 2}, {**good, "stream": "cam3", "seq": 4, "angles": b"\0" * 5},
             {**GOOD, "stream": "s2"}, {**good, "angles": np.array([np.inf, 1], "<f4").tobytes()}]
    b = w.decode(_pack({"v": 1, "type": "frames", "frames": items}))
    kinds = [type(x).__name__ if isinstance(x, w.Frame) else x.reason for x in b.items]
    assert kinds == ["Frame", "not_a_map", "bad_type", "bad_type", "bad_length", "Frame", "non_finite"]
    assert (b.items[4].stream, b.items[4].seq) == ("cam3", 4)     # the answer can name the frame it refuses
    assert b.items[5].stream == "s2"                               # v/type inside an element are allowed


@pytest.mark.parametrize("frames,reason", [([], "bad_length"), ("x", "bad_type"), (None, "missing_field"),
                                           ([{}] * (w.MAX_BUNDLE + 1), "bad_length")])
def test_a_bundle_that_is_not_a_list_of_1_to_max_frames_is_rejected_whole(frames, reason):
    d = {"v": 1, "type": "frames"}
    if frames is not None:
        d["frames"] = frames
    with pytest.raises(w.WireError) as ei:
        w.decode(_pack(d), max_bytes=1 << 22)
    assert ei.value.reason == reason


def test_replies_carry_every_kind_of_answer_and_refuse_requests():
    fill = w.FillMsg("a", 1, 0.5, np.ones(2, np.float32), np.array([0, 1], bool), np.zeros(2, np.float32), "ok", "m", 12)
    rs = [fill, w.Drop("b", 3, "conflated"), w.ErrorMsg("width", "too wide", "c", 9)]
    back = w.decode(w.join_replies([w.encode(r) for r in rs]))
    assert isinstance(back, w.Replies) and [type(x) for x in back.items] == [w.FillMsg, w.Drop, w.ErrorMsg]
    assert back.items[0].angles.tolist() == [1.0, 1.0] and back.items[1:] == rs[1:]
    with pytest.raises(w.WireError) as ei:
        w.decode(_pack({"v": 1, "type": "replies", "replies": [{"v": 1, "type": "control", "cmd": "status"}]}))
    assert ei.value.reason == "bad_type"


def test_bundle_fast_path_equals_reading_each_frame_alone(rng):
    """A well-formed bundle is checked as (n, C) arrays at once; it must give exactly the frames
    the element-by-element path gives, and leave every irregular bundle to that path."""
    from daemon.block import read_block

    C = 6
    def elem(i, masked):
        a = rng.normal(size=C).astype(np.float32)
        obs = rng.random(C) > 0.3
        d = {"stream": f"p{i}", "seq": 10 + i, "t": 0.25 * i}
        if masked:
            a[~obs] = rng.choice([np.nan, np.inf, 7.0])           # unread slots may hold anything
            d.update(angles=a.tobytes(), observed=obs.astype(np.uint8).tobytes())
        else:
            a[~obs] = np.nan
            d.update(angles=a.tobytes())
        return d

    for masked in (True, False):
        els = [elem(i, masked) for i in range(9)]
        block = read_block(els)
        assert block is not None
        fast = block.frames()
        alone = [w.decode(_pack({"v": 1, "type": "frame", **e})) for e in els]
        for x, y in zip(fast, alone):
            assert (x.stream, x.seq, x.t) == (y.stream, y.seq, y.t)
            assert np.array_equal(x.angles, y.angles, equal_nan=True)
            assert (x.observed is None and y.observed is None) or x.observed.tolist() == y.observed.tolist()
        # irregular bundles fall back (and the slow path then reads or refuses each element)
        for bad in ({"angles": b"\0" * 4 * (C + 1)},              # another width
                    {"observed": b"\2" * C} if masked else {"observed": b"\1" * C},   # bad mask / mixed
                    {"t": float("inf")}, {"stream": "a\nb"}, {"seq": -1}, {"type": "hello"}, {"v": 2},
                    {"angles": np.full(C, np.inf, np.float32).tobytes()}):
            assert read_block(els[:4] + [{**els[4], **bad}] + els[5:]) is None, bad


def test_mutated_bundles_never_raise_anything_but_wire_error():
    """Every single-byte change of the bundle example decodes to a message or raises WireError;
    a bundle that decodes holds only Frames and WireErrors."""
    base = bytearray(FRAMES_S1_S2_SEQ7)
    for i in range(len(base)):
        for val in (0x00, 0xC1, 0xFF, 0x7F, base[i] ^ 0x01):
            b = bytearray(base)
            b[i] = val
            try:
                m = w.decode(bytes(b))
            except w.WireError:
                continue
            if isinstance(m, w.Bundle):
                assert all(isinstance(x, (w.Frame, w.WireError)) for x in m.items)


# ---- positions (hello option) ---------------------------------------------------------------
HELLO_S1_ONE_CHANNEL_POSITIONS = bytes.fromhex(  # docs/PROTOCOL.md, `hello` positions
    "85a17601a474797065a568656c6c6fa673747265616da27331a86368616e6e656c7391a96c66656d75722e7278a970"
    "6f736974696f6e73c3"
)
ACK_S1_JOINTS_ROOT_LFEMUR = bytes.fromhex(  # docs/PROTOCOL.md, `hello-ack` with joints
    "89a17601a474797065a968656c6c6f2d61636ba673747265616da27331a56d6f64656ca477616c6ba86368616e6e656c"
    "7391a96c66656d75722e7278ab706173737468726f75676890a76d697373696e6790a66a6f696e747392a4726f6f74a6"
    "6c66656d7572a7706172656e747392ff00"
)
FILL_S1_SEQ7_TWO_JOINT_POSITIONS = bytes.fromhex(  # docs/PROTOCOL.md, `fill` with positions
    "8ca17601a474797065a466696c6ca673747265616da27331a373657107a174cb3ff8000000000000a6616e676c6573c4"
    "0400005040a666696c6c6564c40101a3737464c4040000003fa6737461747573a26f6ba56d6f64656ca477616c6ba770"
    "726f635f7573cd019ca9706f736974696f6e73c418000000000000603f000000000000003e0000003f00000000"
)


def test_protocol_examples_positions():
    h = w.Hello("s1", ["lfemur.rx"], positions=True)
    assert w.encode(h) == HELLO_S1_ONE_CHANNEL_POSITIONS and w.decode(HELLO_S1_ONE_CHANNEL_POSITIONS) == h
    ack = w.HelloAck("s1", "walk", ["lfemur.rx"], joints=["root", "lfemur"], parents=[-1, 0])
    assert w.encode(ack) == ACK_S1_JOINTS_ROOT_LFEMUR and w.decode(ACK_S1_JOINTS_ROOT_LFEMUR) == ack
    f = w.decode(FILL_S1_SEQ7_TWO_JOINT_POSITIONS)
    assert isinstance(f, w.FillMsg) and f.positions.dtype == np.float32
    assert f.positions.tolist() == [[0.0, 0.875, 0.0], [0.125, 0.5, 0.0]]
    assert w.encode(f) == FILL_S1_SEQ7_TWO_JOINT_POSITIONS
    with pytest.raises(w.WireError) as e:  # not a whole number of joints
        w.decode(FILL_S1_SEQ7_TWO_JOINT_POSITIONS[:-26] + bytes.fromhex("c414") + bytes(20))
    assert e.value.reason == "bad_length"


def test_positions_option_on_the_wire():
    """The hello option and the fill field encode and decode; absent means off."""
    h = w.decode(w.encode(w.Hello("s1", ["a.rx"], positions=True)))
    assert h.positions is True
    assert w.decode(w.encode(w.Hello("s1", ["a.rx"]))).positions is False
    assert b"positions" not in w.encode(w.Hello("s1", ["a.rx"]))
    with pytest.raises(w.WireError) as e:
        w.decode(msgpack.packb({"v": 1, "type": "hello", "stream": "s", "channels": ["a"], "positions": 1}))
    assert e.value.reason == "bad_type"
    p = np.arange(6, dtype=np.float32).reshape(2, 3)
    f = w.FillMsg("s1", 1, 0.0, np.zeros(1, np.float32), np.zeros(1, bool), np.zeros(1, np.float32), "ok", "m", 5,
                     positions=p)
    back = w.decode(w.encode(f))
    assert back.positions.shape == (2, 3) and np.array_equal(back.positions, p)
    ack = w.decode(w.encode(w.HelloAck("s1", "m", ["a.rx"], joints=["root", "a"], parents=[-1, 0])))
    assert ack.joints == ["root", "a"] and ack.parents == [-1, 0]
