"""The representation models learn in, and its exact causal inverse.  One place for all of it.

Raw channels (what the studio sends) -> features (what models see):

* constant channels (clavicles, fingers in CMU data) are dropped and restored on the way out;
* angles (``*.rx|ry|rz``) are unwrapped along time: the first frame is mapped into
  (centre - 180, centre + 180] around the training circular mean, later frames continue
  continuously (``u_t = u_{t-1} + wrap(x_t - u_{t-1})``);
* root motion (``root_mode="relative"``, Taylor et al. 2006 section 3): ground-plane
  translation becomes a displacement in the heading frame of the previous frame
  (``root.dside``, ``root.dfwd``), height stays absolute (``root.ty``), orientation about the
  vertical becomes a yaw rate (``root.dyaw``) and the other two rotations absolute pitch and
  roll relative to the heading (``root.pitch``, ``root.roll``);
* optional per-channel normalisation to zero mean and unit variance (stored with the model).

Root dropouts (relative mode).  A root velocity feature is observed only when the root was
observed in this frame *and* the previous one: the first frame after a root gap would otherwise
"see" the whole gap's error as one frame's displacement.  While the root is missing the decoder
integrates the filled displacement and yaw rate from the last completed frame (no jump at the
first erased frame), damped by exp(-(g / ``root_tau``)^q / q) after g missing frames (q =
``root_power``: 1 an exponential decay, 2 a Gaussian one that keeps the motion of short gaps and
stops that of long ones; ``root_tau`` = 0: undamped), so a long root gap falls back toward
holding the last root.  With ``root_turn`` b > 0 the damping's rate follows how the performer
was turning when the root went missing: tau = 1 / (b |w|) for the ground motion and
1 / (1 / ``root_tau`` + b |w|) for the heading (``root_tau`` then damps the heading alone), w the yaw rate
(radians per frame) observed before the gap, an exponential average over ``root_turn_frames``
frames of the frames whose yaw rate was observed (frozen over the gap).  A performer walking
straight keeps walking (on straight walks undamped integration is 7x better than tau 40); one
who was turning, whose heading the gap makes a guess, is held (a turning walk's future is not in
its past).  The heading uncertainty reading: heading spread sigma(g) = g / tau, and the mean of
cos(sigma) is exp(-sigma^2 / 2), the Gaussian damping (q = 2).  The reported std of the
ground position and of the heading is summed over the gap (the errors of successive increments
are taken as fully correlated), each frame adding its damped increment's std and the part of
the increment the damping dropped, not one frame's std.  With ``root_std`` [a, p, c, w, u] the
ground position's std is instead a g^(p-1) (Q(g) + c g) after g missing frames, Q summed over the
gap of the filled speed (the part the damping kept weighted w, the part it dropped 1) and of u x
the damped increments' own std (the summed std is [1, 1, 0, 0, 1]): fitted
on VALIDATION (``bench/hlm_root_std_fit.py``), where the summed std was 1.00 within 2 std on walks
and turns and 0.70 on the run.

The encoder/decoder pair is a *stream*: arrays of shape (n_streams, ...) so the daemon can
code many streams in one call.  ``encode`` maps frame t to features using the previous
*completed* frame; the model fills the missing features; ``decode`` maps them back, passes the
observed raw channels through exactly, and commits the completed frame as the new state.
``transform`` (whole recording, everything observed) equals running the stream, tested.

Conventions for the root (CMU ASF, Y up): orientation matrix R = Rz(rz) Ry(ry) Rx(rx) and the
heading decomposition R = Ry(yaw) Rx(pitch) Rz(roll).  Another skeleton's root (BVH ``Hips``, z
up, ``Zrotation Xrotation Yrotation``...) is described by ``root`` (``mocap.skelmap``'s root
spec, found from the channel names by the skeleton map) and brought into that frame by
``mocap.rootframe``; ``root`` None is CMU ASF's ``root.*``, as in model files written before.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lacuna.errors import LacunaError
from mocap.rootrot import _matrix_to_rxyz, _matrix_to_ypr, _rxyz_to_matrix, _ypr_to_matrix, wrap180  # noqa: F401

ROOT_ROT = ("root.rx", "root.ry", "root.rz")
ROOT_POS = ("root.tx", "root.ty", "root.tz")
ROOT_FEATURES = ("root.dside", "root.ty", "root.dfwd", "root.dyaw", "root.pitch", "root.roll")
CONST_TOL = 1e-2  # degrees: range below this is constant (the rebuilt subject-35 files differ by ~1e-4)


def is_angle(name: str) -> bool:
    return name.rsplit(".", 1)[-1] in ("rx", "ry", "rz")


def circular_mean_deg(x: np.ndarray, axis: int = 0) -> np.ndarray:
    r = np.deg2rad(x)
    return np.rad2deg(np.arctan2(np.sin(r).mean(axis), np.cos(r).mean(axis)))


@dataclass
class Representation:
    """Fitted description of the feature space.  Plain data; JSON round trip via to_dict."""

    channels: list[str]                  # raw channels, the model's input/output
    keep: list[bool]                      # raw channel kept (False = constant, restored)
    const_value: list[float]              # value restored for dropped channels
    center: list[float]                   # unwrap centre per raw channel (angles only)
    root_mode: str = "relative"           # "relative" (Taylor) or "raw"
    normalize: bool = True
    mean: list[float] = field(default_factory=list)   # per feature
    std: list[float] = field(default_factory=list)    # per feature
    features: list[str] = field(default_factory=list)
    root: dict[str, Any] | None = None    # root spec (mocap.rootframe); None = CMU ASF's root.*
    root_tau: float = 0.0                 # frames; damping of root motion over a root gap (0 = none)
    root_power: float = 1.0               # shape of that damping (1 exponential, 2 Gaussian)
    unwrap: bool = True                   # False: angles as captured (Taylor's released code's input)
    root_turn: float = 0.0                # b: the damping's rate grows by b |observed yaw rate| (0 = off)
    root_turn_frames: float = 60.0        # frames of the exponential average of that yaw rate
    # [a, p, c, w, u]: a missing root's ground-position std a g^(p-1) (Q(g) + c g) after g frames, Q
    # summed over the gap of the filled speed (the part the damping kept weighted w, the part it
    # dropped 1) and u x the kept part of the model's own std (fitted on VALIDATION,
    # bench/notebook/rootstd-5.md); [] = the older summed std ([1, 1, 0, 0, 1])
    root_std: list[float] = field(default_factory=list)

    # ---- construction -------------------------------------------------------------------------
    @classmethod
    def fit(cls, sequences: Sequence[np.ndarray], channels: Sequence[str], root_mode: str = "relative",
            normalize: bool = True, drop_constant: bool = True, skeleton: Any = None,
            root_tau: float = 0.0, root_power: float = 1.0, unwrap: bool = True, root_turn: float = 0.0,
            root_turn_frames: float = 60.0, root_std: Sequence[float] = ()) -> Representation:
        """sequences: list of (n_frames, n_channels) raw frames.  ``skeleton``: a skeleton map
        (name, file or ``mocap.skelmap.SkeletonMap``) naming the root; else recognised from the
        channel names."""
        if root_mode not in ("relative", "raw"):
            raise ValueError(f"root_mode must be 'relative' or 'raw' (got {root_mode!r})")
        if not (np.isfinite(root_tau) and root_tau >= 0 and np.isfinite(root_power) and root_power > 0):
            raise ValueError(f"root_tau must be >= 0 frames and root_power > 0 (got {root_tau}, {root_power})")
        if not (np.isfinite(root_turn) and root_turn >= 0 and np.isfinite(root_turn_frames) and root_turn_frames >= 1):
            raise ValueError(f"root_turn must be >= 0 and root_turn_frames >= 1 (got {root_turn}, {root_turn_frames})")
        _check_root_std(root_std)
        channels = list(channels)
        allf = np.vstack([np.asarray(s, dtype=np.float64) for s in sequences])
        if allf.shape[1] != len(channels):
            raise ValueError(f"training frames have {allf.shape[1]} columns for {len(channels)} channels")
        ang = np.array([is_angle(c) for c in channels])
        rng = np.where(ang, np.abs(wrap180(allf - allf[:1])).max(0), np.ptp(allf, 0))
        keep = (rng > CONST_TOL) if drop_constant else np.ones(len(channels), bool)
        root = _root_spec(channels, skeleton) if root_mode == "relative" else None
        if root_mode == "relative":
            want = root["rot"] + root["pos"] if root else list(ROOT_ROT + ROOT_POS)
            missing = [c for c in want if c not in channels]
            if missing:
                raise ValueError(f"root_mode 'relative' needs channels {missing}")
            for c in want:
                keep[channels.index(c)] = True
        center = np.where(ang, circular_mean_deg(allf), 0.0)
        rep = cls(channels, keep.tolist(), allf[0].tolist(), center.tolist(), root_mode, normalize, root=root,
                  root_tau=float(root_tau), root_power=float(root_power), unwrap=bool(unwrap),
                  root_turn=float(root_turn), root_turn_frames=float(root_turn_frames),
                  root_std=[float(v) for v in root_std])
        rep.features = rep._feature_names()
        rep.mean = [0.0] * len(rep.features)
        rep.std = [1.0] * len(rep.features)
        if normalize:
            feats = np.vstack([rep.transform(s, normalized=False) for s in sequences])
            mu = feats.mean(0)
            sd = feats.std(0)
            sd = np.where(sd > 1e-8, sd, 1.0)
            rep.mean, rep.std = mu.tolist(), sd.tolist()
            rep.__dict__.pop("_plan_cache", None)  # the plan caches mean/std as arrays
        return rep

    def root_channels(self) -> tuple[list[str], list[str]]:
        """(rotation x, y, z, translation x, y, z) channel names of the root."""
        if self.root is None:
            return list(ROOT_ROT), list(ROOT_POS)
        return list(self.root["rot"]), list(self.root["pos"])

    def _is_root(self, c: str) -> bool:
        if self.root is None:
            return c.startswith("root.")
        return c in self.root["rot"] or c in self.root["pos"]

    def _feature_names(self) -> list[str]:
        names = []
        root_done = False
        for c, k in zip(self.channels, self.keep):
            if self.root_mode == "relative" and self._is_root(c):
                if not root_done:
                    names += list(ROOT_FEATURES)
                    root_done = True
                continue
            if k:
                names.append(c)
        return names

    def to_dict(self) -> dict[str, Any]:
        d = {k: getattr(self, k) for k in ("channels", "keep", "const_value", "center", "root_mode",
                                            "normalize", "mean", "std", "features", "root_tau", "root_power", "unwrap",
                                            "root_turn", "root_turn_frames")}
        if self.root is not None:
            d["root"] = dict(self.root)
        if self.root_std:
            d["root_std"] = list(self.root_std)  # absent in files written before (the summed std)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Representation:
        rep = cls(**{k: d[k] for k in ("channels", "keep", "const_value", "center", "root_mode", "normalize",
                                        "mean", "std", "features")}, root=d.get("root"),
                  root_tau=float(d.get("root_tau", 0.0)), root_power=float(d.get("root_power", 1.0)),
                  unwrap=bool(d.get("unwrap", True)), root_turn=float(d.get("root_turn", 0.0)),
                  root_turn_frames=float(d.get("root_turn_frames", 60.0)),
                  root_std=[float(v) for v in d.get("root_std", [])])
        _check_root_std(rep.root_std)
        n, f = len(rep.channels), len(rep.features)
        for k, want in (("keep", n), ("const_value", n), ("center", n), ("mean", f), ("std", f)):
            if len(getattr(rep, k)) != want:
                raise ValueError(f"representation {k} has {len(getattr(rep, k))} entries, expected {want}")
        if rep.features != rep._feature_names():
            raise ValueError("representation feature names do not match its channels")
        if rep.root_mode not in ("relative", "raw"):
            raise ValueError(f"representation root_mode {rep.root_mode!r} is unknown")
        if not all(np.isfinite(rep.std)) or min(rep.std, default=1.0) <= 0:
            raise ValueError("representation std must be positive and finite")
        if not (np.isfinite(rep.root_tau) and rep.root_tau >= 0 and np.isfinite(rep.root_power) and rep.root_power > 0):
            raise ValueError(f"representation root_tau must be >= 0 and root_power > 0 "
                             f"(got {rep.root_tau}, {rep.root_power})")
        if not (np.isfinite(rep.root_turn) and rep.root_turn >= 0 and np.isfinite(rep.root_turn_frames)
                and rep.root_turn_frames >= 1):
            raise ValueError(f"representation root_turn must be >= 0 and root_turn_frames >= 1 "
                             f"(got {rep.root_turn}, {rep.root_turn_frames})")
        return rep

    def with_root_damping(self, root_tau: float, root_power: float, root_turn: float | None = None,
                          root_turn_frames: float | None = None) -> Representation:
        """A copy with another root damping (not learned, so no refit); None keeps that setting."""
        d = self.to_dict()
        d["root_tau"], d["root_power"] = float(root_tau), float(root_power)
        if root_turn is not None:
            d["root_turn"] = float(root_turn)
        if root_turn_frames is not None:
            d["root_turn_frames"] = float(root_turn_frames)
        return Representation.from_dict(d)

    def with_root_std(self, root_std: Sequence[float]) -> Representation:
        """A copy with another root-position std rule ([a, p, c, w, u], or [] for the summed std)."""
        d = self.to_dict()
        d["root_std"] = [float(v) for v in root_std]
        return Representation.from_dict(d)

    # ---- index plumbing -----------------------------------------------------------------------
    @property
    def n_features(self) -> int:
        return len(self.features)

    def _plan(self) -> dict[str, Any]:
        if not hasattr(self, "_plan_cache"):
            ch = self.channels
            pos = {c: i for i, c in enumerate(ch)}
            direct_raw, direct_feat = [], []
            for j, f in enumerate(self.features):
                if f in pos and not (self.root_mode == "relative" and (f in ROOT_FEATURES or self._is_root(f))):
                    direct_raw.append(pos[f])
                    direct_feat.append(j)
            # unwrap False: no channel is treated as an angle on the way in or out
            angle = np.array([is_angle(c) for c in ch]) & bool(self.unwrap)
            self._plan_cache = {
                "direct_raw": np.array(direct_raw, int),
                "direct_feat": np.array(direct_feat, int),
                "direct_angle": angle[np.array(direct_raw, int)] if direct_raw else np.zeros(0, bool),
                "dropped": np.flatnonzero(~np.asarray(self.keep)),
                "rot": np.array([pos[c] for c in self.root_channels()[0]], int) if self.root_mode == "relative" else None,
                "pos": np.array([pos[c] for c in self.root_channels()[1]], int) if self.root_mode == "relative" else None,
                "frame": _root_frame(self.root),
                "rootf": np.array([self.features.index(c) for c in ROOT_FEATURES], int)
                if self.root_mode == "relative" else None,
                "center": np.asarray(self.center, dtype=np.float64),
                "center_row": np.asarray(self.center, dtype=np.float64)[None, :],
                "const_row": np.asarray(self.const_value, dtype=np.float64)[None, :],
                "any_angle": bool(angle[np.array(direct_raw, int)].any()) if direct_raw else False,
                "mean": np.asarray(self.mean),
                "std": np.asarray(self.std),
            }
        return self._plan_cache

    def feature_source(self) -> list[list[int]]:
        """For each feature, the raw channels it is computed from at the current frame."""
        pos = {c: i for i, c in enumerate(self.channels)}
        out = []
        if self.root_mode == "relative":
            rot, tr = self.root_channels()
            up = "xyz".index((self.root or {}).get("up", "y"))
            ground = [pos[c] for i, c in enumerate(tr) if i != up]
        for f in self.features:
            if self.root_mode == "relative" and f in ROOT_FEATURES:
                out.append({"root.dside": ground, "root.dfwd": ground,
                            "root.ty": [pos[tr[up]]]}.get(f, [pos[c] for c in rot]))
            else:
                out.append([pos[f]])
        return out

    def _source_index(self) -> tuple[np.ndarray, np.ndarray]:
        """(F, 3) raw-channel index per feature, padded by repeating the first source, and
        (C, 3) feature index per raw channel, padded with F (a zero column): lookup tables so
        that the per-frame masks and stds are one fancy-indexing operation each."""
        if not hasattr(self, "_src_cache"):
            src = self.feature_source()
            fsrc = np.array([s + [s[0]] * (3 - len(s)) for s in src], int).reshape(len(src), 3)
            per_raw: list[list[int]] = [[] for _ in self.channels]
            for j, s in enumerate(src):
                for c in s:
                    per_raw[c].append(j)
            F = len(src)
            rsrc = np.array([r + [F] * (3 - len(r)) for r in per_raw], int).reshape(len(self.channels), 3)
            self._src_cache = (fsrc, rsrc)
        return self._src_cache

    def feature_observed(self, observed: np.ndarray) -> np.ndarray:
        """(n, n_channels) raw mask -> (n, n_features) mask: a feature is observed when all its sources are."""
        observed = np.atleast_2d(observed)
        return observed[:, self._source_index()[0]].all(2)

    def raw_std(self, fstd: np.ndarray) -> np.ndarray:
        """(n, F) feature std in feature units (not normalised) -> (n, C) raw channel std: each
        raw channel takes the largest std of the features computed from it; dropped constant
        channels get 0."""
        fstd = np.atleast_2d(fstd)
        padded = np.concatenate([fstd, np.zeros((fstd.shape[0], 1))], 1)
        return padded[:, self._source_index()[1]].max(2)

    def normalize_features(self, f: np.ndarray) -> np.ndarray:
        p = self._plan()
        return (f - p["mean"]) / p["std"]

    def denormalize_features(self, z: np.ndarray) -> np.ndarray:
        p = self._plan()
        return z * p["std"] + p["mean"]

    # ---- whole recordings ---------------------------------------------------------------------
    def transform(self, frames: np.ndarray, normalized: bool | None = None) -> np.ndarray:
        """(n_frames, n_channels) fully observed raw -> (n_frames, n_features)."""
        st = self.new_state(1)
        frames = np.asarray(frames, dtype=np.float64)
        out = np.empty((frames.shape[0], self.n_features))
        obs = np.ones((1, frames.shape[1]), bool)
        for t in range(frames.shape[0]):
            f, _ = st.encode(frames[t : t + 1], obs, normalized=False)
            out[t] = f[0]
            st.commit(frames[t : t + 1])
        norm = self.normalize if normalized is None else normalized
        return self.normalize_features(out) if norm else out

    def inverse(self, feats: np.ndarray, first: np.ndarray | None = None, normalized: bool | None = None) -> np.ndarray:
        """(n_frames, n_features) -> raw frames, integrating root motion from ``first`` (raw frame 0)."""
        norm = self.normalize if normalized is None else normalized
        feats = self.denormalize_features(feats) if norm else np.asarray(feats, dtype=np.float64)
        st = self.new_state(1)
        if first is not None:
            st.commit(np.asarray(first, dtype=np.float64)[None])
            st.started[:] = False  # frame 0 still encodes as zero motion relative to itself
        out = np.empty((feats.shape[0], len(self.channels)))
        none = np.zeros((1, len(self.channels)), bool)
        for t in range(feats.shape[0]):
            out[t] = st.decode(feats[t : t + 1], np.full((1, len(self.channels)), np.nan), none, normalized=False)[0]
            st.commit(out[t : t + 1])
        return out

    def new_state(self, n_streams: int = 1) -> ReprState:
        return ReprState(self, n_streams)


class ReprState:
    """Causal encoder/decoder state for n streams: the previous completed frame's unwrapped angles,
    root position and yaw, and of the root's dropout (``root_st`` (n, 4): frames the root has been
    missing before this frame, the std summed over them of the ground position and the yaw, and the
    exponential average of the observed yaw rate, degrees per frame, that ``root_turn`` reads)."""

    def __init__(self, rep: Representation, n: int):
        self.rep = rep
        self.n = n
        C = len(rep.channels)
        self.prev_u = np.tile(np.asarray(rep.center, dtype=np.float64), (n, 1))  # unwrapped angles
        self.prev_raw = np.tile(np.asarray(rep.const_value, dtype=np.float64), (n, 1))
        self.prev_yaw = np.zeros(n)          # radians, unwrapped
        self.started = np.zeros(n, bool)     # has a completed frame been committed
        self.root_st = np.zeros((n, 4))      # [frames missing, position std, yaw std (degrees), yaw rate]
        self._C = C

    @classmethod
    def of(cls, rep: Representation, prev_u: np.ndarray, prev_raw: np.ndarray, prev_yaw: np.ndarray,
           started: np.ndarray, root_st: np.ndarray | None = None) -> ReprState:
        """A state over existing arrays (n, C), (n, C), (n,), (n,), (n, 4): writes go to them (views
        of a model's state pool, see ``mocap.feature_model``)."""
        st = cls.__new__(cls)
        st.rep, st.n, st._C = rep, started.shape[0], len(rep.channels)
        st.prev_u, st.prev_raw, st.prev_yaw, st.started = prev_u, prev_raw, prev_yaw, started
        st.root_st = np.zeros((st.n, 4)) if root_st is None else root_st
        return st

    def reset(self, i: int) -> None:
        rep = self.rep
        self.prev_u[i] = rep.center
        self.prev_raw[i] = rep.const_value
        self.prev_yaw[i] = 0.0
        self.started[i] = False
        self.root_st[i] = 0.0

    def _unwrap(self, x: np.ndarray) -> np.ndarray:
        """Raw angles (n, C) -> continuous with the previous frame (or the centre at the start)."""
        ref = np.where(self.started[:, None], self.prev_u, self.rep._plan()["center_row"])
        return ref + wrap180(x - ref)

    def encode(self, frames: np.ndarray, observed: np.ndarray, normalized: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(n, C) raw frames + mask -> (n, F) features + (n, F) feature mask.  Unobserved features are NaN."""
        rep, p = self.rep, self.rep._plan()
        frames = np.asarray(frames, dtype=np.float64)
        observed = np.asarray(observed, dtype=bool)
        x = np.where(observed, frames, np.nan)
        F = np.full((self.n, rep.n_features), np.nan)
        dr, df = p["direct_raw"], p["direct_feat"]
        vals = x[:, dr]
        if p["any_angle"]:
            nan_x = np.isnan(x)
            u = self._unwrap(np.where(nan_x, 0.0, x))
            # angle features take the unwrapped value where the channel was sent (NaN stays NaN)
            vals = np.where(p["direct_angle"] & ~nan_x[:, dr], u[:, dr], vals)
        F[:, df] = vals
        if rep.root_mode == "relative":
            F[:, p["rootf"]] = self._encode_root(x, p)
        fobs = rep.feature_observed(observed) & ~np.isnan(F)
        F = np.where(fobs, F, np.nan)
        norm = rep.normalize if normalized is None else normalized
        if norm:
            F = rep.normalize_features(F)
        return F, fobs

    def _encode_root(self, x: np.ndarray, p: dict[str, Any]) -> np.ndarray:
        fr = p["frame"]
        rot, pos = x[:, p["rot"]], fr.to_canonical(x[:, p["pos"]])
        out = np.full((self.n, 6), np.nan)
        r = np.deg2rad(rot)
        yaw, pitch, roll = _matrix_to_ypr(fr.matrix(r))
        yaw_u = self.prev_yaw + np.deg2rad(wrap180(np.rad2deg(yaw - self.prev_yaw)))
        dyaw = np.where(self.started, np.rad2deg(yaw_u - self.prev_yaw), 0.0)
        prev_pos = fr.to_canonical(self.prev_raw[:, p["pos"]])
        d = np.where(self.started[:, None], pos - prev_pos, 0.0)
        cy, sy = np.cos(self.prev_yaw), np.sin(self.prev_yaw)
        # local = Ry(yaw_prev)^T d  (ground plane x, z)
        side = cy * d[:, 0] - sy * d[:, 2]
        fwd = sy * d[:, 0] + cy * d[:, 2]
        out[:, 0], out[:, 1], out[:, 2] = side, pos[:, 1], fwd
        out[:, 3], out[:, 4], out[:, 5] = dyaw, np.rad2deg(pitch), np.rad2deg(roll)
        # after a root gap the previous root is a fill: no displacement or yaw rate is observed
        out[np.ix_(self.root_st[:, 0] > 0, [0, 2, 3])] = np.nan
        return out

    def decode(self, feats: np.ndarray, frames: np.ndarray, observed: np.ndarray, normalized: bool | None = None) -> np.ndarray:
        """Completed features (n, F) -> raw (n, C); observed raw channels are passed through exactly.
        Does not commit: call ``commit`` with the result."""
        rep, p = self.rep, self.rep._plan()
        norm = rep.normalize if normalized is None else normalized
        Fv = rep.denormalize_features(feats) if norm else np.asarray(feats, dtype=np.float64)
        out = np.repeat(p["const_row"], self.n, axis=0)
        dr, df = p["direct_raw"], p["direct_feat"]
        vals = Fv[:, df]
        ang = p["direct_angle"]
        vals = np.where(ang[None, :], wrap180(vals), vals)
        out[:, dr] = vals
        if rep.root_mode == "relative":
            self._decode_root(Fv[:, p["rootf"]], out, p)
        observed = np.asarray(observed, dtype=bool)
        return np.where(observed, frames, out)

    def _damping(self) -> tuple[np.ndarray, np.ndarray]:
        """(ground motion's, heading's) damping for a root missing g frames before this one:
        exp(-(g / root_tau)^q / q) both (1 without damping); with root_turn b > 0, exp(-(g r)^q / q)
        with r = b |yaw rate| for the ground motion and r = b |yaw rate| + 1 / root_tau for the
        heading (module doc)."""
        tau, q, b = self.rep.root_tau, self.rep.root_power, self.rep.root_turn
        if b > 0:
            rate = b * np.abs(np.deg2rad(self.root_st[:, 3]))
            ks = np.exp(-((self.root_st[:, 0] * rate) ** q) / q)
            kh = np.exp(-((self.root_st[:, 0] * (rate + 1.0 / tau)) ** q) / q) if tau > 0 else ks
            return ks, kh
        k = np.exp(-((self.root_st[:, 0] / tau) ** q) / q) if tau > 0 else np.ones(self.n)
        return k, k

    def _damped(self) -> bool:
        return self.rep.root_tau > 0 or self.rep.root_turn > 0

    def _decode_root(self, rf: np.ndarray, out: np.ndarray, p: dict[str, Any]) -> None:
        side, height, fwd, dyaw, pitch, roll = (rf[:, i] for i in range(6))
        if self._damped():
            k, kh = self._damping()
            side, fwd, dyaw = side * k, fwd * k, dyaw * kh
        yaw = np.where(self.started, self.prev_yaw + np.deg2rad(dyaw), self.prev_yaw)
        cy, sy = np.cos(self.prev_yaw), np.sin(self.prev_yaw)
        dx = cy * side + sy * fwd
        dz = -sy * side + cy * fwd
        fr = p["frame"]
        prev_pos = fr.to_canonical(self.prev_raw[:, p["pos"]])
        st = self.started
        pc = np.empty((self.n, 3))
        pc[:, 0] = np.where(st, prev_pos[:, 0] + dx, prev_pos[:, 0])
        pc[:, 1] = height
        pc[:, 2] = np.where(st, prev_pos[:, 2] + dz, prev_pos[:, 2])
        out[:, p["pos"]] = fr.from_canonical(pc)
        R = _ypr_to_matrix(yaw, np.deg2rad(pitch), np.deg2rad(roll))
        out[:, p["rot"]] = fr.angles(R, self.prev_raw[:, p["rot"]])

    def finish(self, feats: np.ndarray, fstd: np.ndarray, frames: np.ndarray, observed: np.ndarray,
               normalized: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
        """decode + the raw std (0 where observed) + commit: completed features and their std (n, F)
        -> (completed raw frames, raw std), (n, C) each.  In relative mode the std of a missing
        root's ground position and heading is summed over the root gap (module doc)."""
        rep, p = self.rep, self.rep._plan()
        norm = rep.normalize if normalized is None else normalized
        out = self.decode(feats, frames, observed, normalized=norm)
        fsd = np.asarray(fstd, dtype=np.float64) * p["std"] if norm else np.asarray(fstd, dtype=np.float64)
        observed = np.asarray(observed, dtype=bool)
        std = np.where(observed, 0.0, rep.raw_std(fsd))
        sums = None
        if rep.root_mode == "relative":
            rf = fsd[:, p["rootf"]]
            rv = (rep.denormalize_features(feats) if norm else np.asarray(feats, dtype=np.float64))[:, p["rootf"]]
            k, kh = self._damping()
            # the damped increments' own std, and the motion the damping dropped (the performer may
            # well keep moving: the spread between holding and integrating)
            sy = self.root_st[:, 2] + kh * rf[:, 3] + (1.0 - kh) * np.abs(rv[:, 3])
            if rep.root_std:
                # the calibrated rule: a g^(p-1) (Q + c g), Q summed over the gap in root_st[:, 1]
                # (in place of the summed std): the filled (undamped) speed, its kept part weighted
                # w, and u x the kept part of the model's std
                a, pw, c, w, u = rep.root_std
                g1 = self.root_st[:, 0] + 1.0
                acc = self.root_st[:, 1] + (w * k + (1.0 - k)) * np.hypot(rv[:, 0], rv[:, 2]) + u * k * np.maximum(rf[:, 0], rf[:, 2])
                sp = a * g1 ** (pw - 1.0) * (acc + c * g1)
            else:
                acc = sp = (self.root_st[:, 1] + k * np.maximum(rf[:, 0], rf[:, 2])
                            + (1.0 - k) * np.hypot(rv[:, 0], rv[:, 2]))
            pos, rot = p["pos"][[0, 2]], p["rot"]
            std[:, pos] = np.where(observed[:, pos], 0.0, sp[:, None])
            std[:, rot] = np.where(observed[:, rot], 0.0, np.maximum(std[:, rot], sy[:, None]))
            sums = (acc, sy)
        self.commit(out, observed=observed, sums=sums)
        return out, std

    def commit(self, completed: np.ndarray, rows: np.ndarray | None = None, observed: np.ndarray | None = None,
               sums: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Make the completed raw frames (n, C) the new previous frame.  With ``observed`` (n, C)
        (relative mode) the root's dropout is counted: a frame with any root channel missing adds
        one to the gap (and ``sums``, the stds summed so far, are kept), a fully observed root
        resets it, and the yaw rate of a frame whose root and previous root were observed enters
        the yaw rate's average (``root_st[:, 3]``).  Without it (a recording with everything
        observed) neither moves."""
        rep, p = self.rep, self.rep._plan()
        completed = np.asarray(completed, dtype=np.float64)
        sel = slice(None) if rows is None else rows
        u = self._unwrap(completed)
        self.prev_u[sel] = u[sel] if rows is not None else u
        self.prev_raw[sel] = completed[sel] if rows is not None else completed
        if rep.root_mode == "relative":
            r = np.deg2rad(completed[:, p["rot"]])
            yaw, _, _ = _matrix_to_ypr(p["frame"].matrix(r))
            yaw_u = self.prev_yaw + np.deg2rad(wrap180(np.rad2deg(yaw - self.prev_yaw)))
            dyaw = np.rad2deg(yaw_u - self.prev_yaw)
            self.prev_yaw[sel] = yaw_u[sel] if rows is not None else yaw_u
            if observed is not None:
                o = np.asarray(observed, dtype=bool)
                seen = o[:, p["rot"]].all(1) & o[:, p["pos"]].all(1)
                st = self.root_st.copy()
                rate = np.where(seen & (st[:, 0] == 0) & self.started,
                                st[:, 3] + (dyaw - st[:, 3]) / rep.root_turn_frames, st[:, 3])
                st[:, 0] += 1.0
                if sums is not None:
                    st[:, 1], st[:, 2] = sums
                st[seen, :3] = 0.0
                st[:, 3] = rate
                self.root_st[sel] = st[sel] if rows is not None else st
        self.started[sel] = True


def _check_root_std(v: Sequence[float]) -> None:
    if len(v) not in (0, 5) or not all(np.isfinite(x) for x in v) or (len(v) == 5 and (v[0] <= 0 or min(v[2:]) < 0)):
        raise ValueError(f"root_std must be [] or [a > 0, p, c >= 0, w >= 0, u >= 0] (got {list(v)})")


def has_root_channels(channels: Sequence[str], skeleton: Any = None) -> bool:
    """Whether these channels carry the root's three rotations and three translations (named
    through their skeleton map, else CMU ASF's root.*): what ``root_mode="relative"`` needs."""
    try:
        spec = _root_spec(channels, skeleton)
    except (ValueError, LacunaError):
        return False
    want = spec["rot"] + spec["pos"] if spec else list(ROOT_ROT + ROOT_POS)
    return all(c in channels for c in want)


def _root_spec(channels: Sequence[str], skeleton: Any) -> dict[str, Any] | None:
    """The root spec of these channels through their skeleton map; None for CMU ASF's root.*."""
    from mocap import skelmap

    try:
        b = skelmap.Binding.of(channels, skeleton)
    except skelmap.SkeletonError:
        if skeleton is not None:
            raise
        return None  # no map fits: the CMU ASF convention, whose channels fit() then requires
    spec = b.root_spec()
    if spec is None and b.map.root_bone != "root":
        r = b.root_bone or b.map.root_bone
        raise ValueError(f"root_mode 'relative' needs the root's rotation and translation channels "
                         f"({r}.rx, .ry, .rz, .tx, .ty, .tz; skeleton {b.map.name})")
    return None if spec is None or spec == skelmap.DEFAULT_ROOT else spec


def _root_frame(spec: dict[str, Any] | None) -> Any:
    from mocap.rootframe import RootFrame

    return RootFrame(spec)


def resample(frames: np.ndarray, src_fps: float, dst_fps: float, channels: Sequence[str] | None = None) -> np.ndarray:
    """Change the frame rate.  An integer ratio keeps every k-th frame, as Taylor et al. do
    (120 -> 30 Hz: frames 0, 4, 8, ...); otherwise angles are unwrapped and linearly interpolated."""
    ratio = src_fps / dst_fps
    if abs(ratio - round(ratio)) < 1e-9 and round(ratio) >= 1:
        return np.asarray(frames)[:: int(round(ratio))].copy()
    frames = np.asarray(frames, dtype=np.float64)
    n = frames.shape[0]
    t_src = np.arange(n) / src_fps
    t_dst = np.arange(0.0, t_src[-1] + 1e-12, 1.0 / dst_fps)
    ang = np.array([is_angle(c) for c in channels]) if channels is not None else np.zeros(frames.shape[1], bool)
    src = frames.copy()
    src[:, ang] = np.rad2deg(np.unwrap(np.deg2rad(src[:, ang]), axis=0))
    out = np.stack([np.interp(t_dst, t_src, src[:, j]) for j in range(frames.shape[1])], 1)
    out[:, ang] = wrap180(out[:, ang])
    return out
