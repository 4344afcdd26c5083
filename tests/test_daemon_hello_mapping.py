"""Performers of one studio say hello with the same channel list: they share one channel
mapping (a mapping is never changed), built once, and each stream still gets its own mapping
when its list differs (daemon/sessions.py ``_mapping``; bench/notebook/gc-10.md)."""
from __future__ import annotations

import numpy as np

from daemon import wire
from daemon.fillers import PassThroughModel
from daemon.sessions import MAPPINGS_KEPT, SessionTable

CH = ["a.x", "a.y", "b.x", "b.y"]


def _table() -> SessionTable:
    model = PassThroughModel(CH)
    return SessionTable(lambda req, sid: ("pt", model), 4 * MAPPINGS_KEPT, lambda name, sid: None)


def test_same_channels_share_one_mapping_and_frames_map_as_before():
    t = _table()
    studio = ["b.y", "a.x", "extra", "b.x"]
    acks = [t.hello(wire.Hello(f"s{i}", list(studio)))[0] for i in range(3)]
    maps = [t.sessions[f"s{i}"].mapping for i in range(3)]
    assert maps[0] is maps[1] is maps[2]
    for ack in acks:
        assert ack.channels == studio and ack.passthrough == ["extra"] and ack.missing == ["a.y"]
    other = t.hello(wire.Hello("s3", list(CH)))[0]
    assert t.sessions["s3"].mapping is not maps[0] and t.sessions["s3"].mapping.identity
    assert other.passthrough == [] and other.missing == []
    mp = maps[0]
    assert np.asarray(CH)[mp.m_idx].tolist() == np.asarray(studio)[mp.s_idx].tolist()


def test_the_kept_mappings_are_bounded():
    t = _table()
    for i in range(3 * MAPPINGS_KEPT):
        t.hello(wire.Hello(f"s{i}", CH + [f"extra{i}"]))
        assert t.sessions[f"s{i}"].mapping.passthrough == [f"extra{i}"]
    assert len(t._maps) <= MAPPINGS_KEPT


def test_a_reload_rebinds_streams_to_shared_mappings_of_the_new_model():
    t = _table()
    studio = ["b.y", "a.x", "b.x", "a.y"]
    for i in range(3):
        t.hello(wire.Hello(f"s{i}", list(studio)))
    new = PassThroughModel(["a.x", "b.x"])
    assert t.rebind("pt", new) == 3
    maps = [t.sessions[f"s{i}"].mapping for i in range(3)]
    assert maps[0] is maps[1] is maps[2] and maps[0].n_model == 2
    assert maps[0].s_idx.tolist() == [1, 2] and maps[0].m_idx.tolist() == [0, 1]
    assert maps[0].passthrough == ["b.y", "a.y"]
