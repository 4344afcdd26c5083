"""The representation's causal encoder/decoder compiled with numba, stream by stream: the same
arithmetic as ``mocap.representation.ReprState.encode`` / ``decode`` / ``commit`` (and the
feature-to-raw std of ``Representation.raw_std``), in two calls per step instead of about a
hundred and fifty numpy calls.  ``mocap.feature_model`` uses it when ``lacuna.jit.enabled()``
(numba importable, LACUNA_NO_JIT unset, JIT code allowed); the numpy code stays the reference
(``tests/test_hlm_fast.py`` checks the two agree frame by frame on real motion, for both root
modes, normalised or not).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from lacuna.jit import jit as _jit


@_jit
def _wrap(x):  # pragma: no cover - compiled
    """(x + 180) % 360 - 180 to the bit; the float modulo (fmod and its sign fix) only outside
    one turn either way, where one exact subtraction or the same single rounding does not serve."""
    y = x + 180.0
    if 0.0 <= y < 360.0:
        return y - 180.0
    if 360.0 <= y < 720.0:
        return (y - 360.0) - 180.0   # exact (Sterbenz), as fmod is
    if -360.0 <= y < 0.0:
        return (y + 360.0) - 180.0   # Python's modulo: fmod(y) = y, then + 360 rounded once
    return y % 360.0 - 180.0


@_jit
def _rxyz(a, b, c, R):  # pragma: no cover - compiled
    ca, sa, cb, sb, cc, sc = math.cos(a), math.sin(a), math.cos(b), math.sin(b), math.cos(c), math.sin(c)
    R[0, 0] = cc * cb
    R[0, 1] = cc * sb * sa - sc * ca
    R[0, 2] = cc * sb * ca + sc * sa
    R[1, 0] = sc * cb
    R[1, 1] = sc * sb * sa + cc * ca
    R[1, 2] = sc * sb * ca - cc * sa
    R[2, 0] = -sb
    R[2, 1] = cb * sa
    R[2, 2] = cb * ca


@_jit
def _asin_clip(v):  # pragma: no cover - compiled
    if v != v:
        return v
    return math.asin(min(max(v, -1.0), 1.0))


@_jit
def _deg(x):  # pragma: no cover - compiled
    return x * (180.0 / math.pi)


@_jit
def _rad(x):  # pragma: no cover - compiled
    return x * (math.pi / 180.0)


@_jit
def encode1(frame, observed, prev_u, prev_raw, prev_yaw, started, root_st, center, dr, df, dang, any_angle,
            relative, rot, pos, rootf, fsrc, normalize, mean, std, F, fobs, x, R):  # pragma: no cover - compiled
    """ReprState.encode for one stream: fills F (n_features,) and fobs (n_features,) in place.
    x (C,) and R (3, 3): working arrays, overwritten (the caller's, made once for a batch: an
    allocation costs more than the arithmetic done in it)."""
    C = frame.shape[0]
    for c in range(C):
        x[c] = frame[c] if observed[c] else np.nan
    for j in range(F.shape[0]):
        F[j] = np.nan
    for k in range(dr.shape[0]):
        c = dr[k]
        v = x[c]
        if any_angle and dang[k] and v == v:
            ref = prev_u[c] if started else center[c]
            v = ref + _wrap(v - ref)
        F[df[k]] = v
    if relative:
        r0, r1, r2 = _rad(x[rot[0]]), _rad(x[rot[1]]), _rad(x[rot[2]])
        _rxyz(r0, r1, r2, R)
        pitch = _asin_clip(-R[1, 2])
        roll = math.atan2(R[1, 0], R[1, 1])
        yaw = math.atan2(R[0, 2], R[2, 2])
        yaw_u = prev_yaw + _rad(_wrap(_deg(yaw - prev_yaw)))
        dyaw = _deg(yaw_u - prev_yaw) if started else 0.0
        d0 = x[pos[0]] - prev_raw[pos[0]] if started else 0.0
        d2 = x[pos[2]] - prev_raw[pos[2]] if started else 0.0
        cy, sy = math.cos(prev_yaw), math.sin(prev_yaw)
        F[rootf[0]] = cy * d0 - sy * d2
        F[rootf[1]] = x[pos[1]]
        F[rootf[2]] = sy * d0 + cy * d2
        F[rootf[3]] = dyaw
        F[rootf[4]] = _deg(pitch)
        F[rootf[5]] = _deg(roll)
        if root_st[0] > 0:
            # after a root gap the previous root is a fill: no displacement or yaw rate observed
            F[rootf[0]] = np.nan
            F[rootf[2]] = np.nan
            F[rootf[3]] = np.nan
    for j in range(F.shape[0]):
        ok = observed[fsrc[j, 0]] and observed[fsrc[j, 1]] and observed[fsrc[j, 2]] and F[j] == F[j]
        fobs[j] = ok
        if not ok:
            F[j] = np.nan
        elif normalize:
            F[j] = (F[j] - mean[j]) / std[j]


@_jit
def _to_rxyz(R, p0, p1, p2, out, i0, i1, i2):  # pragma: no cover - compiled
    b1 = _asin_clip(-R[2, 0])
    a1 = math.atan2(R[2, 1], R[2, 2])
    c1 = math.atan2(R[1, 0], R[0, 0])
    s10, s11, s12 = _deg(a1), _deg(b1), _deg(c1)
    s20, s21, s22 = s10 + 180.0, 180.0 - s11, s12 + 180.0
    d1 = abs(_wrap(s10 - p0)) + abs(_wrap(s11 - p1)) + abs(_wrap(s12 - p2))
    d2 = abs(_wrap(s20 - p0)) + abs(_wrap(s21 - p1)) + abs(_wrap(s22 - p2))
    if d2 < d1:
        out[i0], out[i1], out[i2] = _wrap(s20), _wrap(s21), _wrap(s22)
    else:
        out[i0], out[i1], out[i2] = _wrap(s10), _wrap(s11), _wrap(s12)


@_jit
def finish1(z, zstd, frame, observed, prev_u, prev_raw, prev_yaw, started, root_st, center, const, dr, df, dang,
            relative, rot, pos, rootf, rsrc, normalize, mean, std, root_damp, root_power, out, sd, Fv,
            R):  # pragma: no cover - compiled
    """ReprState.finish (decode + the raw std + commit), for one stream.  Writes the completed raw
    frame to out, its std (0 where observed) to sd, and the new previous-frame state (prev_u,
    prev_raw, root_st in place); returns the new prev_yaw.  root_damp: (root_tau, root_turn,
    root_turn_frames, root_std a, p, c, w, u; a 0 = no root_std) of the representation (``tables``'
    "root_tau").  Fv (n_features,) and R (3, 3): working arrays, overwritten (``encode1``'s x, R)."""
    root_tau, root_turn, turn_frames = root_damp[0], root_damp[1], root_damp[2]
    std_a, std_p, std_c, std_w, std_u = root_damp[3], root_damp[4], root_damp[5], root_damp[6], root_damp[7]
    damped = root_tau > 0 or root_turn > 0
    rate_seen = False
    C = frame.shape[0]
    nF = z.shape[0]
    for j in range(nF):
        Fv[j] = z[j] * std[j] + mean[j] if normalize else z[j]
    for c in range(C):
        out[c] = const[c]
    for k in range(dr.shape[0]):
        v = Fv[df[k]]
        out[dr[k]] = _wrap(v) if dang[k] else v
    kd = 1.0
    rate = 0.0
    if relative and root_turn > 0:
        rate = root_turn * abs(_rad(root_st[3]))
        kd = math.exp(-((root_st[0] * rate) ** root_power) / root_power)
    elif relative and root_tau > 0:
        kd = math.exp(-((root_st[0] / root_tau) ** root_power) / root_power)
    kh = kd                                  # the heading's (ReprState._damping)
    if relative and root_turn > 0 and root_tau > 0:
        kh = math.exp(-((root_st[0] * (rate + 1.0 / root_tau)) ** root_power) / root_power)
    speed, turn = 0.0, 0.0
    if relative:
        side, height, fwd = Fv[rootf[0]], Fv[rootf[1]], Fv[rootf[2]]
        dyaw, pitch, roll = Fv[rootf[3]], Fv[rootf[4]], Fv[rootf[5]]
        speed, turn = math.hypot(side, fwd), abs(dyaw)
        if damped:
            side, fwd, dyaw = side * kd, fwd * kd, dyaw * kh
        yaw = prev_yaw + _rad(dyaw) if started else prev_yaw
        cy, sy = math.cos(prev_yaw), math.sin(prev_yaw)
        dx = cy * side + sy * fwd
        dz = -sy * side + cy * fwd
        out[pos[0]] = prev_raw[pos[0]] + dx if started else prev_raw[pos[0]]
        out[pos[1]] = height
        out[pos[2]] = prev_raw[pos[2]] + dz if started else prev_raw[pos[2]]
        p, r = _rad(pitch), _rad(roll)
        cyy, syy, cp, sp, cr, sr = math.cos(yaw), math.sin(yaw), math.cos(p), math.sin(p), math.cos(r), math.sin(r)
        R[0, 0] = cyy * cr + syy * sp * sr
        R[0, 1] = -cyy * sr + syy * sp * cr
        R[0, 2] = syy * cp
        R[1, 0] = cp * sr
        R[1, 1] = cp * cr
        R[1, 2] = -sp
        R[2, 0] = -syy * cr + cyy * sp * sr
        R[2, 1] = syy * sr + cyy * sp * cr
        R[2, 2] = cyy * cp
        _to_rxyz(R, prev_raw[rot[0]], prev_raw[rot[1]], prev_raw[rot[2]], out, rot[0], rot[1], rot[2])
    for c in range(C):
        if observed[c]:
            out[c] = frame[c]
    # raw std: each raw channel takes the largest std of the features computed from it
    for c in range(C):
        if observed[c]:
            sd[c] = 0.0
            continue
        m = -np.inf
        for i in range(3):
            j = rsrc[c, i]
            v = 0.0 if j >= nF else (zstd[j] * std[j] if normalize else zstd[j])
            if v > m or v != v:
                m = v
                if v != v:
                    break
        sd[c] = m
    if relative:
        # the std of a missing root's ground position and heading, summed over the root gap
        s0 = zstd[rootf[0]] * std[rootf[0]] if normalize else zstd[rootf[0]]
        s2 = zstd[rootf[2]] * std[rootf[2]] if normalize else zstd[rootf[2]]
        s3 = zstd[rootf[3]] * std[rootf[3]] if normalize else zstd[rootf[3]]
        mx = s0 if s0 > s2 else s2
        if s0 != s0 or s2 != s2:
            mx = np.nan                      # np.maximum's NaN
        if std_a > 0:
            # Representation.root_std's rule (ReprState.finish): root_st[1] sums the filled speed
            g1 = root_st[0] + 1.0
            acc = root_st[1] + (std_w * kd + (1.0 - kd)) * speed + std_u * kd * mx
            sp = std_a * g1 ** (std_p - 1.0) * (acc + std_c * g1)
        else:
            sp = root_st[1] + kd * mx + (1.0 - kd) * speed
            acc = sp
        sy = root_st[2] + kh * s3 + (1.0 - kh) * turn
        for i in (0, 2):
            if not observed[pos[i]]:
                sd[pos[i]] = sp
        for i in range(3):
            c = rot[i]
            if not observed[c] and sd[c] == sd[c] and (sy != sy or sy > sd[c]):
                sd[c] = sy
        seen = True
        for i in range(3):
            if not (observed[rot[i]] and observed[pos[i]]):
                seen = False
        rate_seen = seen and root_st[0] == 0.0 and started
        if seen:
            root_st[0], root_st[1], root_st[2] = 0.0, 0.0, 0.0
        else:
            root_st[0], root_st[1], root_st[2] = root_st[0] + 1.0, acc, sy
    # commit: the completed frame becomes the previous one
    for c in range(C):
        ref = prev_u[c] if started else center[c]
        prev_u[c] = ref + _wrap(out[c] - ref)
        prev_raw[c] = out[c]
    new_yaw = prev_yaw
    if relative:
        _rxyz(_rad(out[rot[0]]), _rad(out[rot[1]]), _rad(out[rot[2]]), R)  # (the decode's R is done with)
        yaw2 = math.atan2(R[0, 2], R[2, 2])
        new_yaw = prev_yaw + _rad(_wrap(_deg(yaw2 - prev_yaw)))
        if rate_seen:
            # the observed yaw rate's exponential average (ReprState.commit)
            root_st[3] = root_st[3] + (_deg(new_yaw - prev_yaw) - root_st[3]) / turn_frames
    return new_yaw


@_jit
def encode_many(frames, observed, prev_u, prev_raw, prev_yaw, started, root_st, center, dr, df, dang, any_angle,
                relative, rot, pos, rootf, fsrc, normalize, mean, std, F, fobs):  # pragma: no cover - compiled
    x = np.empty(frames.shape[1])
    R = np.empty((3, 3))
    for i in range(frames.shape[0]):
        encode1(frames[i], observed[i], prev_u[i], prev_raw[i], prev_yaw[i], started[i], root_st[i], center, dr, df, dang,
                any_angle, relative, rot, pos, rootf, fsrc, normalize, mean, std, F[i], fobs[i], x, R)


@_jit
def finish_many(z, zstd, frames, observed, prev_u, prev_raw, prev_yaw, started, root_st, center, const, dr, df, dang,
                relative, rot, pos, rootf, rsrc, normalize, mean, std, root_damp, root_power, out, sd):  # pragma: no cover - compiled
    Fv = np.empty(z.shape[1])
    R = np.empty((3, 3))
    for i in range(frames.shape[0]):
        prev_yaw[i] = finish1(z[i], zstd[i], frames[i], observed[i], prev_u[i], prev_raw[i], prev_yaw[i], started[i],
                              root_st[i], center, const, dr, df, dang, relative, rot, pos, rootf, rsrc, normalize,
                              mean, std, root_damp, root_power, out[i], sd[i], Fv, R)
        started[i] = True


def tables(rep: Any) -> dict[str, Any]:
    """The representation's index plan as the compiled functions take it (cached on rep)."""
    t = rep.__dict__.get("_fast_tables")
    if t is None:
        p = rep._plan()
        fsrc, rsrc = rep._source_index()
        rel = rep.root_mode == "relative"
        z3 = np.zeros(3, np.int64)
        t = rep.__dict__["_fast_tables"] = {
            "center": np.ascontiguousarray(p["center"], np.float64),
            "const": np.ascontiguousarray(p["const_row"][0], np.float64),
            "dr": np.ascontiguousarray(p["direct_raw"], np.int64),
            "df": np.ascontiguousarray(p["direct_feat"], np.int64),
            "dang": np.ascontiguousarray(p["direct_angle"], np.bool_),
            "any_angle": bool(p["any_angle"]),
            "relative": rel,
            "rot": np.ascontiguousarray(p["rot"], np.int64) if rel else z3,
            "pos": np.ascontiguousarray(p["pos"], np.int64) if rel else z3,
            "rootf": np.ascontiguousarray(p["rootf"], np.int64) if rel else np.zeros(6, np.int64),
            "fsrc": np.ascontiguousarray(fsrc, np.int64),
            "rsrc": np.ascontiguousarray(rsrc, np.int64),
            "normalize": bool(rep.normalize),
            "mean": np.ascontiguousarray(p["mean"], np.float64),
            "std": np.ascontiguousarray(p["std"], np.float64),
            # (root_tau, root_turn, root_turn_frames, root_std's a, p, c, w, u): one array, so the kernels
            # that pass it on (hlm.fast's) keep their signatures
            "root_tau": np.array([rep.root_tau, rep.root_turn, rep.root_turn_frames,
                                  *(rep.root_std or (0.0, 1.0, 0.0, 0.0, 1.0))], np.float64),
            "root_power": float(rep.root_power),
        }
    return t


def encode(rs: Any, frames: np.ndarray, observed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ReprState.encode of state rs (n streams) for frames, observed (n, C): features, mask (n, F)."""
    t = tables(rs.rep)
    n = frames.shape[0]
    nF = rs.rep.n_features
    F = np.empty((n, nF))
    fobs = np.empty((n, nF), np.bool_)
    encode_many(np.ascontiguousarray(frames, np.float64), np.ascontiguousarray(observed, np.bool_), rs.prev_u,
                rs.prev_raw, rs.prev_yaw, rs.started, rs.root_st, t["center"], t["dr"], t["df"], t["dang"], t["any_angle"],
                t["relative"], t["rot"], t["pos"], t["rootf"], t["fsrc"], t["normalize"], t["mean"], t["std"], F, fobs)
    return F, fobs


def finish(rs: Any, z: np.ndarray, zstd: np.ndarray, frames: np.ndarray, observed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """decode + commit + the raw std (0 where observed) for n streams; returns (completed, std), (n, C) each.
    The state's arrays are written in place (they may be views of a model's state pool)."""
    t = tables(rs.rep)
    n, C = frames.shape
    out = np.empty((n, C))
    sd = np.empty((n, C))
    finish_many(np.ascontiguousarray(z, np.float64), np.ascontiguousarray(zstd, np.float64),
                np.ascontiguousarray(frames, np.float64), np.ascontiguousarray(observed, np.bool_), rs.prev_u,
                rs.prev_raw, rs.prev_yaw, rs.started, rs.root_st, t["center"], t["const"], t["dr"], t["df"], t["dang"],
                t["relative"], t["rot"], t["pos"], t["rootf"], t["rsrc"], t["normalize"], t["mean"], t["std"],
                t["root_tau"], t["root_power"], out, sd)
    return out, sd
