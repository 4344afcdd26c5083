"""Encode, for a bundle served as arrays: its fills written as msgpack straight from the tick's
arrays by one compiled call, the very bytes msgpack packs the fill maps to (issue 19's vectorised
wire path; daemon/tickblock.py builds the maps only where this does not serve).

Each row is the map ``{"v": 1, "type": "fill", "stream", "seq", "t", "angles", "filled", "std",
"status", "model", "proc_us"[, "style"][, "phase"][, "gap"]}`` in that key order, as
daemon/tickblock.py builds it and :func:`daemon.pack.fill_map` would: ints in msgpack's smallest
form, floats as doubles, byte strings as bin.  The constant pieces (keys, the model's name,
the statuses, ``proc_us``, each stream id) are packed by msgpack itself, once; the kernel copies
them and writes the numbers and the arrays' bytes between them.  tests/test_daemon_rowpack.py
checks the bytes against msgpack's on fuzzed rows, and the block path's fuzz test
(tests/test_daemon_wire_block.py) compares what two daemons send.

(A numpy version of this, a structured array of the rows' fixed-size fields, was tried and
reverted in stop 39: ten numpy calls a tick cost more after the live wait than msgpack's one
pass over 64 maps.  This is one compiled call.)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from lacuna import jit

_PACK = msgpack.Packer(use_bin_type=True).pack
_U8 = np.dtype(np.uint8)
_HEAD = np.frombuffer(b"".join(_PACK(x) for x in ("v", 1, "type", "fill", "stream")), _U8)
_KEYS = [_PACK(k) for k in ("seq", "t", "angles", "filled", "std", "status", "model", "proc_us", "style", "phase", "gap")]
_KEY_BLOB = np.frombuffer(b"".join(_KEYS), _U8)
_KEY_AT = np.cumsum([0] + [len(k) for k in _KEYS]).astype(np.int64)
SIDS_KEPT = 4096  # packed stream ids kept (cleared when full)


@dataclass(eq=False)
class Rows:
    """A bundle's fills encoded: ``data`` the rows' msgpack maps back to back, row i ending at
    ``ends[i]``; ``sids`` each row's stream (PUB's topic)."""

    data: bytes
    ends: list[int]
    sids: list[str]

    def __len__(self) -> int:
        return len(self.ends)

    def row(self, i: int) -> bytes:
        return self.data[(self.ends[i - 1] if i else 0):self.ends[i]]


class RowPack:
    """The daemon's encoder of bundled fills (its packed stream ids cached); ``on`` False
    without the compiler (``LACUNA_NO_JIT=1``): the maps serve."""

    def __init__(self) -> None:
        self.on = jit.enabled()
        self._sid: dict[str, bytes] = {}
        self._const: dict[Any, np.ndarray] = {}
        if self.on:  # compiled (or loaded from numba's cache) now, at start, with the types a tick gives it
            z = np.zeros((1, 2), np.float32)
            self.encode(["a"], [300], [1.0], z, np.zeros((1, 2), np.bool_), z, None, "ok", "m", 1, z, [0.5], [1])
            self._sid.clear()
            self._const.clear()

    def encode(self, sids: list[str], seqs: list[int], stamps: list[float], angles: np.ndarray, filled: np.ndarray | None,
               std: np.ndarray | None, statuses: list[str] | None, status: str, model: str, proc_us: int,
               style: np.ndarray | None, phases: Any, gaps: list[int] | None) -> Rows:
        """Rows i < n: ``angles`` (n, C) float32, ``filled`` (n, C) bool and ``std`` (n, C)
        float32 or None (zeros: a pass-through's), ``statuses`` one a row or None (``status`` for
        all), ``style`` (n, K) float32 or None, ``phases`` a finite float a row (list or array) or None,
        ``gaps`` an int a row (written where > 0) or None."""
        n, C = angles.shape
        sp = self._sid
        if len(sp) > SIDS_KEPT:
            sp.clear()
        packed = [sp.get(s) or sp.setdefault(s, _PACK(s)) for s in sids]
        sid_blob = np.frombuffer(b"".join(packed), _U8)
        sid_at = np.zeros(n + 1, np.int64)
        np.cumsum([len(b) for b in packed], out=sid_at[1:])
        if statuses is None:
            names, st_idx = [status], np.zeros(n, np.int64)
        else:
            names = sorted(set(statuses))
            st_idx = np.array([names.index(s) for s in statuses], np.int64) if len(names) > 1 else np.zeros(n, np.int64)
        tail = self._tail(tuple(names), model)  # status strings, then "model" key + name + "proc_us" key
        st_blob, st_at = tail
        proc = _PACK(int(proc_us))
        K = 0 if style is None else style.shape[1]
        has_phase = phases is not None
        ph = np.array(phases if has_phase else [0.0], np.float64).view(np.uint64)  # (a copy: the kernel reads its bits)
        gp = np.array(gaps if gaps is not None else [0], np.int64)
        zero = np.zeros((1, 1), _U8)
        size = n * (len(_HEAD) + int(_KEY_AT[-1]) + int(st_at[-1]) + len(proc) + 9 * C + 4 * K + 80) + int(sid_at[-1])
        out = np.empty(size, _U8)
        ends = np.empty(n, np.int64)
        _rows_kernel(out, ends, _HEAD, sid_blob, sid_at, _KEY_BLOB, _KEY_AT, st_blob, st_at, st_idx,
                     np.frombuffer(proc, _U8), np.array(seqs, np.int64),
                     np.array(stamps, np.float64).view(np.uint64), np.ascontiguousarray(angles).view(_U8),
                     zero if filled is None else np.ascontiguousarray(filled).view(_U8),
                     zero if std is None else np.ascontiguousarray(std).view(_U8), 0 if std is None else 1,
                     zero if style is None else np.ascontiguousarray(style).view(_U8), K, ph,
                     1 if has_phase else 0, gp, 0 if gaps is None else 1, C)
        e = ends.tolist()
        return Rows(out[:e[-1]].tobytes() if n else b"", e, sids)

    def _tail(self, names: tuple[str, ...], model: str) -> tuple[np.ndarray, np.ndarray]:
        key = (names, model)
        got = self._const.get(key)
        if got is None:
            if len(self._const) > 64:
                self._const.clear()
            parts = [_PACK(s) for s in names] + [_PACK("model") + _PACK(model) + _PACK("proc_us")]
            blob = np.frombuffer(b"".join(parts), _U8)
            at = np.cumsum([0] + [len(p) for p in parts]).astype(np.int64)
            got = self._const[key] = (blob, at)  # type: ignore[assignment]
        return got  # type: ignore[return-value]


def _put_uint(out: Any, p: Any, x: Any) -> Any:  # pragma: no cover - compiled
    """msgpack's smallest form of an int x >= 0 at out[p:]; returns the next p."""
    if x < 128:
        out[p] = x
        return p + 1
    if x < 256:
        out[p] = 0xCC
        out[p + 1] = x
        return p + 2
    if x < 65536:
        out[p] = 0xCD
        w = 2
    elif x < 4294967296:
        out[p] = 0xCE
        w = 4
    else:
        out[p] = 0xCF
        w = 8
    for j in range(w):
        out[p + 1 + j] = (x >> (8 * (w - 1 - j))) & 255
    return p + 1 + w


def _bin_head(out: Any, p: Any, w: Any) -> Any:  # pragma: no cover - compiled
    """msgpack's bin header for w bytes (w < 65536 here: MAX_CHANNELS float32s) at out[p:]."""
    if w < 256:
        out[p] = 0xC4
        out[p + 1] = w
        return p + 2
    out[p] = 0xC5
    out[p + 1] = w >> 8
    out[p + 2] = w & 255
    return p + 3


def _put_bin(out: Any, p: Any, src: Any, i: Any, w: Any) -> Any:  # pragma: no cover - compiled
    """msgpack bin of src[i, :w] at out[p:]."""
    p = _bin_head(out, p, w)
    for j in range(w):
        out[p + j] = src[i, j]
    return p + w


def _put_zeros(out: Any, p: Any, w: Any) -> Any:  # pragma: no cover - compiled
    """msgpack bin of w zero bytes at out[p:] (a pass-through's filled mask and std)."""
    p = _bin_head(out, p, w)
    for j in range(w):
        out[p + j] = 0
    return p + w


def _put_f64(out: Any, p: Any, u: Any) -> Any:  # pragma: no cover - compiled
    out[p] = 0xCB
    for j in range(8):
        out[p + 1 + j] = (u >> np.uint64(56 - 8 * j)) & np.uint64(255)
    return p + 9


def _copy(out: Any, p: Any, src: Any, a: Any, b: Any) -> Any:  # pragma: no cover - compiled
    for j in range(a, b):
        out[p] = src[j]
        p += 1
    return p


def _rows(out: Any, ends: Any, head: Any, sid_blob: Any, sid_at: Any, key_blob: Any, key_at: Any, st_blob: Any, st_at: Any,
          st_idx: Any, proc: Any, seqs: Any, stamps: Any, angles: Any, filled: Any, std: Any, has_std: Any, style: Any, K: Any,
          phases: Any, has_phase: Any, gaps: Any, has_gap: Any, C: Any) -> Any:  # pragma: no cover - compiled
    n = seqs.shape[0]
    S = st_at.shape[0] - 2  # (the status strings; the last part is "model" + name + "proc_us")
    p = 0
    for i in range(n):
        g = gaps[i] if has_gap else 0
        out[p] = 0x80 | (11 + (1 if K > 0 else 0) + has_phase + (1 if g > 0 else 0))
        p = _copy(out, p + 1, head, 0, head.shape[0])
        p = _copy(out, p, sid_blob, sid_at[i], sid_at[i + 1])
        p = _copy(out, p, key_blob, key_at[0], key_at[1])  # "seq"
        p = _put_uint(out, p, seqs[i])
        p = _copy(out, p, key_blob, key_at[1], key_at[2])  # "t"
        p = _put_f64(out, p, stamps[i])
        p = _copy(out, p, key_blob, key_at[2], key_at[3])  # "angles"
        p = _put_bin(out, p, angles, i, 4 * C)
        p = _copy(out, p, key_blob, key_at[3], key_at[4])  # "filled"
        p = _put_bin(out, p, filled, i, C) if has_std else _put_zeros(out, p, C)
        p = _copy(out, p, key_blob, key_at[4], key_at[5])  # "std"
        p = _put_bin(out, p, std, i, 4 * C) if has_std else _put_zeros(out, p, 4 * C)
        p = _copy(out, p, key_blob, key_at[5], key_at[6])  # "status"
        k = st_idx[i]
        p = _copy(out, p, st_blob, st_at[k], st_at[k + 1])
        p = _copy(out, p, st_blob, st_at[S], st_at[S + 1])  # "model", the name, "proc_us"
        p = _copy(out, p, proc, 0, proc.shape[0])
        if K > 0:
            p = _copy(out, p, key_blob, key_at[8], key_at[9])  # "style"
            p = _put_bin(out, p, style, i, 4 * K)
        if has_phase:
            p = _copy(out, p, key_blob, key_at[9], key_at[10])  # "phase"
            p = _put_f64(out, p, phases[i])
        if g > 0:
            p = _copy(out, p, key_blob, key_at[10], key_at[11])  # "gap"
            p = _put_uint(out, p, g)
        ends[i] = p
    return p


_put_uint = jit.jit(_put_uint)
_bin_head = jit.jit(_bin_head)
_put_bin = jit.jit(_put_bin)
_put_zeros = jit.jit(_put_zeros)
_put_f64 = jit.jit(_put_f64)
_copy = jit.jit(_copy)
_rows_kernel = jit.jit(_rows)
