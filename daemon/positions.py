"""Joint positions in the fills of a stream whose ``hello`` asked for them (``positions: true``).

The model file's training skeleton (``model.meta["training"]["skeleton"]``, see docs/SKELETONS.md)
gives a :class:`mocap.fk.Kinematics` over the model's channels, built once per model object.
Each such stream gets a :class:`StreamFK` with its own buffers: per fill it copies the completed
frame into a float64 model-space buffer (observed values as sent, the model's values elsewhere,
model channels the studio does not send from the model's frame), runs the compiled
``Kinematics.position`` into a (J, 3) buffer and returns it as float32, the one array it
allocates.  Streams that did not ask have ``Session.fk = None``: one check per fill, no work.
"""
from __future__ import annotations

import weakref
from typing import Any

import numpy as np

from lacuna.filler import Model

NO_SKELETON = "no_skeleton"  # the hello error reason

_KIN: weakref.WeakKeyDictionary[Model, Any] = weakref.WeakKeyDictionary()


def kinematics(model: Model, name: str) -> Any:
    """The model's Kinematics over its own channels.  ValueError (the hello error's detail)
    when the model carries no skeleton record or its record does not give FK."""
    kin = _KIN.get(model)
    if kin is not None:
        return kin
    meta = getattr(model, "meta", None) or {}
    rec = (meta.get("training") or {}).get("skeleton") if isinstance(meta, dict) else None
    if not isinstance(rec, dict) or not model.channels:
        raise ValueError(f"model {name!r} ({model.method}) carries no training skeleton, so its fills cannot "
                         "carry positions (train it from ASF/AMC or BVH takes with `lacuna train hlm|crbm`)")
    from mocap.fk import from_record

    try:
        kin = from_record(rec, list(model.channels))
    except Exception as e:  # noqa: BLE001 - a damaged record is the client's answer, not a daemon crash
        raise ValueError(f"model {name!r}: its training skeleton does not give forward kinematics "
                         f"({type(e).__name__}: {e})"[:300]) from None
    kin.position(np.zeros(len(kin.channels)), out=np.empty((len(kin.joints), 3)))  # compile now, not on a frame
    _KIN[model] = kin
    return kin


def warm(model: Model, name: str) -> None:
    """At model load (start, reload thread): build and compile the model's FK if it carries a
    skeleton, so a hello asking for positions does not stall the serving loop compiling it.  A
    model without one (or with a damaged one) loads as before; its hellos get ``no_skeleton``."""
    try:
        kinematics(model, name)
    except ValueError:
        pass


class StreamFK:
    """One stream's FK: its kinematics, its studio -> model channel map, its buffers."""

    def __init__(self, kin: Any, s_idx: np.ndarray, m_idx: np.ndarray, identity: bool):
        self.kin = kin
        self.joints: list[str] = list(kin.joints)
        self.parents: list[int] = list(kin.parents)
        self._identity = identity
        self._s_idx, self._m_idx = s_idx, m_idx
        self._frame = np.zeros(len(kin.channels))                # model-space completed frame
        self._take = np.zeros(s_idx.size, np.float32)            # the reply's values of model channels
        self._out = np.zeros((len(kin.joints), 3))               # metres, float64

    def __call__(self, model_frame: np.ndarray, angles: np.ndarray) -> np.ndarray:
        """(J, 3) float32 positions of the completed frame: ``angles`` the reply's (studio order,
        observed values as sent), ``model_frame`` the model's own completed frame."""
        b = self._frame
        if self._identity:
            np.copyto(b, angles)
        else:
            np.copyto(b, model_frame)  # model channels the studio does not send: the model's values
            np.take(angles, self._s_idx, out=self._take, mode="clip")  # (indices are in range: no check)
            np.put(b, self._m_idx, self._take)
        self.kin.position(b, out=self._out)
        return self._out.astype(np.float32)


def stream_fk(model: Model, name: str, mapping: Any) -> StreamFK:
    """A StreamFK for a session's model and channel mapping (ValueError: no skeleton)."""
    return StreamFK(kinematics(model, name), mapping.s_idx, mapping.m_idx, mapping.identity)
