"""The view's feed without a browser: joint states from masks and stds, channel names, newest
frame wins, positions from mocap.fk (issue 20, part 3)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from daemon import wire
from mocap.datasets import load_trial
from mocap.fk import Kinematics
from view.feed import HELD, OBSERVED, Feed, Skeleton, dumps


@pytest.fixture(scope="module")
def take(data):
    return load_trial("07_01")


@pytest.fixture(scope="module")
def skel(take):
    return Skeleton.from_motion(take)


def fill(sid, seq, frame, filled=None, std=None, t=0.0, proc_us=100, style=None, phase=None):
    C = len(frame)
    f = np.zeros(C, bool) if filled is None else filled
    s = np.zeros(C, np.float32) if std is None else np.asarray(std, np.float32)
    return wire.FillMsg(sid, seq, t, np.asarray(frame, np.float32), f, s, "ok", "m", proc_us,
                        None if style is None else np.asarray(style, np.float32), phase)


def test_joint_state_is_observed_held_or_the_largest_std_of_its_filled_channels(take, skel):
    ch = take.channels
    cmap = skel.mapping(ch)
    C = len(ch)
    filled = np.zeros(C, bool)
    std = np.zeros(C)
    hum = [i for i, c in enumerate(ch) if c.startswith("rhumerus.")]
    filled[hum] = True
    std[hum] = [2.0, 7.5, 3.0]
    rad = ch.index("rradius.rx")
    filled[rad], std[rad] = True, np.nan  # held: no estimate
    fem = ch.index("lfemur.ry")
    filled[fem], std[fem] = True, 4.0  # only one of the joint's three channels filled
    state = dict(zip(skel.joints, cmap.joint_state(filled, std)))
    assert state["rhumerus"] == 7.5 and state["rradius"] == HELD and state["lfemur"] == 4.0
    assert all(v == OBSERVED for j, v in state.items() if j not in ("rhumerus", "rradius", "lfemur"))


def test_stream_channels_in_another_order_land_on_the_skeleton_by_name(take, skel):
    """A studio's channel order (here reversed, and without the root translation) is mapped by
    name; positions equal mocap.fk's on the take's own frame, missing channels from the file."""
    ch = list(reversed([c for c in take.channels if not c.startswith("root.t")]))
    feed = Feed(skel, ch)
    k = 40
    frame = take.frames[k, take.index(ch)]
    feed.on_fill(fill("s", k, frame))
    upd = feed.tick()
    pos = np.array(upd["streams"][0]["pos"]).reshape(-1, 3)
    want_frame = take.frames[k].copy()
    roots = [take.channels.index(c) for c in ("root.tx", "root.ty", "root.tz")]
    want_frame[roots] = take.frames[0, roots]  # the stream lacks them: the skeleton file's first frame
    want = Kinematics.from_motion(take).position(want_frame)
    assert np.abs(pos - want).max() < 1e-3  # positions are sent rounded to 0.1 mm (float32 angles)


def test_newest_frame_wins_and_a_tick_sends_only_streams_that_changed(take, skel):
    feed = Feed(skel)
    for seq in range(5):
        feed.on_fill(fill("a", seq, take.frames[seq], proc_us=1000 * (seq + 1)))
    feed.on_fill(fill("b", 0, take.frames[0]))
    upd = feed.tick()
    by = {d["id"]: d for d in upd["streams"]}
    assert by["a"]["seq"] == 4 and by["b"]["seq"] == 0
    assert by["a"]["proc_ms"] == 5.0  # the largest of the tick's frames
    assert upd["stats"]["a"]["frames"] == 5
    feed.on_fill(fill("b", 1, take.frames[1]))
    upd = feed.tick()
    assert [d["id"] for d in upd["streams"]] == ["b"]
    assert feed.tick() is None  # nothing new, no stats due
    json.loads(dumps(upd))


def test_capture_to_view_age_only_for_wall_clock_timestamps(take, skel):
    feed = Feed(skel)
    feed.on_fill(fill("live", 0, take.frames[0], t=1000.0), wall=1000.004)
    feed.on_fill(fill("replay", 0, take.frames[0], t=0.5), wall=1000.0)
    by = {d["id"]: d for d in feed.tick()["streams"]}
    assert by["live"]["age_ms"] == pytest.approx(4.0, abs=0.01) and by["replay"]["age_ms"] is None


def test_style_and_phase_pass_through_and_a_stream_without_names_says_why(take, skel):
    feed = Feed(skel)
    feed.on_fill(fill("h", 0, take.frames[0], style=[0.25, 0.75], phase=0.5))
    feed.on_fill(fill("odd", 0, np.zeros(7)))
    by = {d["id"]: d for d in feed.tick()["streams"]}
    assert by["h"]["style"] == [0.25, 0.75] and by["h"]["phase"] == 0.5
    assert "pos" not in by["odd"]
    meta = {m["id"]: m for m in feed.meta()["streams"]}
    assert "channel names unknown" in meta["odd"]["problem"] and meta["h"]["drawn"]
    # a hello-ack on the PUB names the channels: the stream is drawn from then on
    feed.on_ack(wire.HelloAck("odd", "m", list(take.channels[:7])))
    feed.on_fill(fill("odd", 1, take.frames[1, :7]))
    d = feed.tick()["streams"][0]
    assert d["id"] == "odd" and len(d["pos"]) == 3 * len(skel.joints)


def test_feed_refuses_a_rate_of_zero(skel):
    with pytest.raises(ValueError, match="--rate"):
        Feed(skel, rate=0)


def test_a_stream_without_frames_for_a_while_is_forgotten(take, skel, monkeypatch):
    import view.feed as vf

    feed = Feed(skel)
    feed.on_fill(fill("gone", 0, take.frames[0]))
    feed.on_fill(fill("here", 0, take.frames[0]))
    feed.tick()
    v = feed.meta_version
    now = vf.time.monotonic()
    monkeypatch.setattr(vf.time, "monotonic", lambda: now + vf.FORGET_S + 1)
    feed.on_fill(fill("here", 1, take.frames[1]))
    feed.tick()
    assert [m["id"] for m in feed.meta()["streams"]] == ["here"] and feed.meta_version > v


def test_a_stream_whose_width_changes_is_mapped_again(take, skel):
    """A new hello over the ROUTER (the view does not see its ack) may change a stream's channel
    list: the view looks for the names again instead of indexing the old map."""
    feed = Feed(skel)
    feed.on_fill(fill("s", 0, take.frames[0]))
    assert "pos" in feed.tick()["streams"][0]
    feed.on_fill(fill("s", 1, take.frames[1, :5]))
    d = feed.tick()["streams"][0]
    assert "pos" not in d and "channel names unknown" in feed.meta()["streams"][0]["problem"]
    feed.on_fill(fill("s", 2, take.frames[2]))
    assert "pos" in feed.tick()["streams"][0] and feed.meta()["streams"][0]["problem"] == ""
