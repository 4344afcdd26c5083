"""A superseded frame set aside within a burst, kept as what its answer needs.

Under a backlog most frames of a burst are superseded by a newer frame of their stream and
answered after the turn's fills (daemon/dispatch.py, ``SessionTable.replay``).  Their answer
(``drop`` conflated, late or duplicate) depends only on the frame's stream, seq, capture time
and width, so a well-formed one is kept as ``(seq, t)``, read once from its unpacked map
(:func:`head`, under exactly the conditions of daemon/decode.py's fast path, which builds the
``Frame``), and replayed without decoding it, a run of them in one loop (``SessionTable.take_run``).  Anything else (a frame
the fast path would not take, one of another sender or width) keeps its map and is decoded and
taken at its turn in the replay as before, so its answer (an ``error``, say) is the same.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from daemon.block import no_inf
from daemon.schema import F32, MAX_CHANNELS, MAX_SEQ, MAX_STREAM_ID, SCHEMA_VERSION

Head = tuple[int, float, int]  # (seq, t, width) of a well-formed frame
NO_ANGLES = np.empty(0, F32)  # a replayed frame's angles: SessionTable.take_run does not read them
_ADD = np.add.reduce


def head(m: dict[str, Any]) -> Head | None:
    """(seq, t, width) of a frame map that daemon/decode.py's ``_decode_frame`` takes on its fast
    path (the same checks, in the same order; keep the two alike), else None."""
    v, sid, seq, t, b, ob = m.get("v"), m.get("stream"), m.get("seq"), m.get("t"), m.get("angles"), m.get("observed")
    if not (m.get("type") == "frame" and type(v) is int and v == SCHEMA_VERSION
            and type(sid) is str and 0 < len(sid) <= MAX_STREAM_ID and type(seq) is int and 0 <= seq <= MAX_SEQ
            and type(t) is float and math.isfinite(t) and type(b) is bytes and 0 < len(b) <= 4 * MAX_CHANNELS
            and not len(b) % 4 and sid.isprintable()):
        return None
    if ob is None:
        if no_inf(b) or not np.isinf(np.frombuffer(b, dtype=F32)).any():
            return seq, t, len(b) // 4
    elif type(ob) is bytes and 4 * len(ob) == len(b) and not ob.translate(None, b"\x00\x01"):
        if math.isfinite(_ADD(np.frombuffer(b, dtype=F32), where=np.frombuffer(ob, dtype=np.bool_),
                              dtype=np.float64)):
            return seq, t, len(b) // 4
    return None


def keep(m: Any, s: Any, who: Any) -> Head | None:
    """The head of frame map ``m`` of session ``s`` from principal ``who`` when it can be replayed
    without decoding (well formed, its owner's, its width), else None (it keeps its map)."""
    h = head(m) if type(m) is dict else None
    if h is not None and (s.owner == who or who is None) and h[2] == s.mapping.n_in:
        return h
    return None


def chain_of(maps: list[Any], items: list[Any], order: list[int], served: int, s: Any,
             principal: Any) -> list[Any]:
    """The chain ``SessionTable.replay`` takes for the frames ``order`` (indices into the
    burst's ``maps`` and ``items``, arrival order) of ``s``, ``served`` the one served: None for
    it, a run of consecutive kept heads as one list of (seq, t, origin, arrived) (taken by
    ``SessionTable.take_run`` in one loop), anything else as (map, origin, arrived)."""
    chain: list[Any] = []
    for d in order:
        if d == served:
            chain.append(None)
            continue
        _, origin, arrived = items[d]
        h = keep(maps[d], s, principal(origin))
        if h is None:
            chain.append((maps[d], origin, arrived))
        elif chain and type(chain[-1]) is list:
            chain[-1].append((h[0], h[1], origin, arrived))
        else:
            chain.append([(h[0], h[1], origin, arrived)])
    return chain


def missing(width: int) -> np.ndarray:
    """``width`` missing values: a stand-in frame's angles."""
    return np.full(width, np.nan, F32)
