"""A superseded frame set aside within a burst, kept as what its answer needs.

Under a backlog most frames of a burst are superseded by a newer frame of their stream and
answered after the turn's fills (daemon/dispatch.py, ``SessionTable.replay``).  Their answer
(``drop`` conflated, late or duplicate) depends only on the frame's stream, seq, capture time
and width, so a well-formed one is kept as ``(seq, t)``, read once from its unpacked map
(:func:`head`, by daemon/decode.py's fast-path check ``well_formed``, which builds the
``Frame`` there), and replayed without decoding it, a run of them in one loop (``SessionTable.take_run``).  Anything else (a frame
the fast path would not take, one of another sender or width) keeps its map and is decoded and
taken at its turn in the replay as before, so its answer (an ``error``, say) is the same.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from daemon.decode import well_formed
from daemon.schema import F32, SCHEMA_VERSION

Head = tuple[int, float, int]  # (seq, t, width) of a well-formed frame
NO_ANGLES = np.empty(0, F32)  # a replayed frame's angles: SessionTable.take_run does not read them


def head(m: dict[str, Any]) -> Head | None:
    """(seq, t, width) of a frame map of this schema version that daemon/decode.py takes on its
    fast path (``well_formed``), else None."""
    v = m.get("v")
    if not (m.get("type") == "frame" and type(v) is int and v == SCHEMA_VERSION):
        return None
    got = well_formed(m)
    return None if got is None else (got[1], got[2], got[3].size)


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
