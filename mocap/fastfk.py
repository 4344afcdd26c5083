"""``Kinematics.position`` for one frame compiled with numba: the arithmetic of
``Kinematics.positions`` (mocap.fk) joint by joint on 3x3 arrays, without numpy's per-call
overhead (a live view calls it every frame of every stream).  ``mocap.fk`` uses it when
``lacuna.jit.enabled()``; tests/test_fk.py checks the two agree."""
from __future__ import annotations

import math

import numpy as np

from lacuna.jit import jit as _jit


@_jit
def _mul(A, B, out):  # pragma: no cover - compiled
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@_jit
def _elem(axis, rad, E):  # pragma: no cover - compiled
    c, s = math.cos(rad), math.sin(rad)
    for i in range(3):
        for j in range(3):
            E[i, j] = 0.0
    E[axis, axis] = 1.0
    i, j = (1, 2) if axis == 0 else ((2, 0) if axis == 1 else (0, 1))
    E[i, i] = c
    E[j, j] = c
    E[i, j] = -s
    E[j, i] = s


@_jit
def position1(frame, cols, axes, r0, r1, parents, off, t0, t1, tcols, taxes, pre, post, has_pre, own, unit,
              R, out):  # pragma: no cover - compiled
    """Fill out (J, 3) metres for one frame (C,); R (J, 3, 3) is scratch."""
    J = parents.shape[0]
    L = np.empty((3, 3))
    E = np.empty((3, 3))
    T = np.empty((3, 3))
    o = np.empty(3)
    for j in range(J):
        for a in range(3):
            for b in range(3):
                L[a, b] = 1.0 if a == b else 0.0
        for k in range(r0[j], r1[j]):
            _elem(axes[k], frame[cols[k]] * (math.pi / 180.0), E)
            _mul(L, E, T)
            L[:, :] = T
        if has_pre[j]:
            _mul(pre[j], L, T)
            _mul(T, post[j], L)
        for a in range(3):
            o[a] = off[j, a]
        for k in range(t0[j], t1[j]):
            o[taxes[k]] += frame[tcols[k]]
        p = parents[j]
        if p < 0:
            R[j, :, :] = L
            for a in range(3):
                out[j, a] = o[a]
            continue
        _mul(R[p], L, R[j])
        q = j if own else p
        for a in range(3):
            out[j, a] = out[p, a] + R[q, a, 0] * o[0] + R[q, a, 1] * o[1] + R[q, a, 2] * o[2]
    for j in range(J):
        for a in range(3):
            out[j, a] *= unit


def tables(kin) -> tuple:
    """The Kinematics' layout as flat arrays for ``position1``."""
    cols, axes, r0, r1, tcols, taxes, t0, t1 = [], [], [], [], [], [], [], []
    for rot, tr in zip(kin._rot, kin._trans):
        r0.append(len(cols))
        for c, a in rot:
            if c >= 0:
                cols.append(c)
                axes.append(a)
        r1.append(len(cols))
        t0.append(len(tcols))
        for c, a in tr:
            tcols.append(c)
            taxes.append(a)
        t1.append(len(tcols))
    i = lambda v: np.asarray(v, np.int64)  # noqa: E731
    return (i(cols), i(axes), i(r0), i(r1), i(kin.parents), np.ascontiguousarray(kin._off), i(t0), i(t1), i(tcols),
            i(taxes), np.ascontiguousarray(kin._pre), np.ascontiguousarray(kin._post), np.asarray(kin._has_pre, bool),
            bool(kin._own))
