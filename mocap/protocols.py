"""Fill protocols as code: training data, test sequences, which channels are erased from which
frame, and the metric.  ``get_protocol(name)`` returns one; ``lacuna eval`` runs it.

pan2009     Pan & Torresani 2009 section 4.3: train on CMU 07_02, 07_09, 07_10 and every
            subject-35 trial (120 Hz); test 07_01; over its second half erase every channel
            except the 14 leg channels; metric: mean squared wrapped error per erased angle
            channel (degrees^2), root translation scored separately.
            ``Pan2009(split="validation")`` scores the same erasure on the walks of the
            validation split (07_10, 35_28, walking_20, walking_21) with a model trained on the
            paper's training set minus every validation and test take (``train_split``, implied);
            ``Pan2009(train_split=True)`` trains on that reduced set for ``--test`` files too.
taylor2007  Taylor, Hinton & Roweis 2006 section 5 on the split in cmu35_taylor (30 Hz): tests
            35_29 (walk) and 35_18 (jog); from the middle on erase the right leg (7 channels)
            or the upper body (36); metric: cumulative scaled error and RMS degrees.
gaps        Seeded random occlusion that looks like a real take: bursts of dropout of 0.1-2 s on
            joint groups (arms, legs, head and neck, torso, root), several at once.  Trained on
            ``splits.TRAIN`` (locomotion and non-locomotion), scored on ``splits.VALIDATION``
            (default) or ``splits.TEST``.

Any protocol scores other recordings with ``cases(test_files=[...], asf=...)``.  Every case
carries ``info["cm_per_unit"]`` (from the ASF's ``:units length``; see mocap.metrics) and the
common scoring of ``mocap.metrics`` applies to all; ``Protocol.score`` adds the protocol's own
figures (pan2009's MSE, taylor2007's cumulative scaled error).
"""
from __future__ import annotations

import functools
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lacuna.errors import DataError
from mocap import datasets, skelmap, splits
from mocap.metrics import cm_per_unit
from mocap.motion import Motion
from mocap.representation import CONST_TOL, is_angle, resample, wrap180

# Joint groups come from the skeleton maps (mocap/skeletons/*.toml); these are CMU ASF's, for
# callers that name bones of the protocols' own data.
_CMU = skelmap.load("cmu-asf")
JOINT_GROUPS = {g: tuple(b for b, i in _CMU.bones.items() if i.part == g and b != "lhipjoint" and b != "rhipjoint")
                for g in skelmap.GROUPS}
LEG_BONES = JOINT_GROUPS["left-leg"] + JOINT_GROUPS["right-leg"]
# the gaps protocol also drops the root (pelvis markers occluded: its rotation and translation)
GAP_GROUPS = {**JOINT_GROUPS, "root": ("root",)}
GAP_BINS = ((0.1, 0.25), (0.25, 0.5), (0.5, 1.0), (1.0, 2.0))


@functools.cache
def load_take(name: str) -> Motion:
    """A named take (``splits.load_take``), parsed once per process; its frames are read-only."""
    m = splits.load_take(name)
    m.frames.flags.writeable = False
    return m


def _as_list(test_files: str | list[str] | None) -> list[str]:
    if test_files is None:
        return []
    return [test_files] if isinstance(test_files, (str, Path)) else [str(f) for f in test_files]


def named_training_set(names: list[str]) -> TrainingSet:
    """The named takes (``splits.take_path``: CMU's layout or ``cmu_li``) as a TrainingSet labelled by activity."""
    ms = [load_take(t) for t in names]
    labels = [splits.ACTIVITY.get(t, "walk") for t in names]
    return TrainingSet([m.frames for m in ms], ms[0].channels, 120.0, list(names), labels)


def bone(ch: str) -> str:
    return ch.split(".", 1)[0]


def _cm_per_unit(m: Motion, b: skelmap.Binding) -> float | None:
    """cm per file length unit: the ASF's, else the skeleton map's (CMU BVH) or mocap.fk's guess."""
    u = cm_per_unit(m.skeleton)
    if u is None and m.skeleton is not None:
        from mocap.fk import Kinematics

        u = 100.0 * (b.map.length_unit or Kinematics.from_motion(m).length_unit)
    return u


def _skeleton_info(b: skelmap.Binding, skeleton: Any = None) -> dict[str, Any]:
    """A case's joint groups (group -> the take's bone names), root translation channels, and
    forward kinematics (``fk``, for the joint-position error) when the take has a skeleton."""
    from mocap.fk import Kinematics

    spec = b.root_spec()
    out: dict[str, Any] = {"groups": {g: tuple(b.bones(g)) for g in GAP_GROUPS}, "skeleton": b.map.name}
    if spec:
        out["root_translation"] = tuple(spec["pos"])
    if skeleton is not None:
        out["fk"] = Kinematics.from_skeleton(skeleton, b.channels, skeleton_map=b.map)
    return out


def erase_bursts(obs: np.ndarray, cols: Any, group: str, rng: np.random.Generator, fps: float, lead_s: float,
                 rate_per_s: float, lo_s: float, hi_s: float, bursts: list[tuple[str, int, int]]) -> None:
    """Erase ``cols`` of the (T, C) mask ``obs`` in bursts, in place: onsets a Poisson process of
    ``rate_per_s`` starting ``lead_s`` in, durations log-uniform in [lo_s, hi_s]; each burst is
    appended to ``bursts`` as (group, start, stop).  The gaps protocol's dropouts, also drawn by
    blend/fit.py for fitting `default`'s weights."""
    T = obs.shape[0]
    t = fps * (lead_s + rng.exponential(1.0 / rate_per_s))
    while t < T:
        dur = np.exp(rng.uniform(np.log(lo_s), np.log(hi_s)))
        a, b = int(t), min(T, int(t + dur * fps))
        if b > a:
            obs[a:b, cols] = False
            bursts.append((group, a, b))
        t = b + fps * rng.exponential(1.0 / rate_per_s)


@dataclass
class TrainingSet:
    """sequences: list of (n_frames, n_channels) raw frames (degrees), all on ``channels``."""

    sequences: list[np.ndarray]
    channels: list[str]
    fps: float
    names: list[str]
    labels: list[str] = field(default_factory=list)
    skeleton: str | None = None  # --skeleton NAME|FILE of the takes (None: recognised from the bone names)

    @property
    def n_frames(self) -> int:
        return sum(s.shape[0] for s in self.sequences)


@dataclass
class Case:
    """One scored fill.

    truth : (T, C) ground-truth raw frames.  observed : (T, C) bool mask given to the filler.
    scored : (C,) bool, channels whose errors count.  ``erased`` names the erasure pattern.
    """

    test: str
    erased: str
    truth: np.ndarray
    observed: np.ndarray
    channels: list[str]
    fps: float
    scored: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def missing(self) -> np.ndarray:
        return ~self.observed


def _row(case: Case, metric: str, value: float) -> dict[str, Any]:
    return {"test": case.test, "erased": case.erased, "metric": metric, "value": float(value)}


def wrapped_error(case: Case, filled: np.ndarray) -> np.ndarray:
    """(T, C) error: wrapped for angle channels, plain for translations."""
    err = np.asarray(filled, dtype=np.float64) - case.truth
    ang = np.array([is_angle(c) for c in case.channels])
    err[:, ang] = wrap180(err[:, ang])
    return err


class Protocol:
    name = "?"
    description = ""
    options: dict[str, Any] = {}
    skeleton: str | None = None  # --skeleton NAME|FILE for test files (else recognised by bone names)

    def binding(self, m: Motion) -> skelmap.Binding:
        """The skeleton map applied to a take's channels (its joint groups and root)."""
        return skelmap.Binding.of(m.channels, self.skeleton, m.source)

    def training_set(self) -> TrainingSet:
        raise NotImplementedError

    def cases(self, test_files: str | list[str] | None = None, asf: str | None = None) -> list[Case]:
        raise NotImplementedError

    def score(self, case: Case, filled: np.ndarray) -> list[dict[str, Any]]:
        """The protocol's own figures (the common ones are mocap.metrics')."""
        return []

    # shared helper
    def _load_file(self, path: str, asf: str | None, fps: float, channels: list[str]) -> Motion:
        from mocap.io import read_motion
        from mocap.tpose import skip_tpose

        p = str(path)
        if not Path(p).is_file():
            raise DataError(f"{p}: no such file")
        m = skip_tpose(read_motion(p, asf=asf))
        missing = [c for c in channels if c not in m.channels]
        if missing and self.binding(m).map.name != _CMU.name:
            # another skeleton (a BVH take): its own channels, erased through its map; the model
            # must have been trained on that skeleton
            frames = m.frames if abs(m.fps - fps) <= 1e-6 else resample(m.frames, m.fps, fps, m.channels)
            return Motion(frames, list(m.channels), fps, m.skeleton, p, dict(m.meta))
        if missing:
            raise DataError(f"{p}: lacks channels the protocol needs, e.g. {missing[:3]}")
        frames = m.frames[:, m.index(channels)]
        if abs(m.fps - fps) > 1e-6:
            frames = resample(frames, m.fps, fps, channels)
        return Motion(frames, list(channels), fps, m.skeleton, p)

    def _load_files(self, test_files, asf: str | None, fps: float, channels: list[str]) -> list[Motion]:
        return [self._load_file(f, asf, fps, channels) for f in _as_list(test_files)]

    def files_training_set(self, files: list[str], asf: str | None = None) -> TrainingSet:
        """A training set of the given takes (any one skeleton; a leading T-pose skipped), at the
        protocol's frame rate, labelled by activity where ``splits`` knows the take."""
        from mocap.io import read_motion
        from mocap.tpose import skip_tpose

        fps = float(self.options.get("fps", 120.0))
        seqs, names, ch = [], [], None
        for f in _as_list(files):
            if not Path(f).is_file():
                raise DataError(f"{f}: no such file")
            m = skip_tpose(read_motion(f, asf=asf))
            if ch is None:
                ch = m.channels
            elif m.channels != ch:
                raise DataError(f"{f}: channels differ from {files[0]}'s: train on takes of one skeleton")
            seqs.append(m.frames if abs(m.fps - fps) <= 1e-6 else resample(m.frames, m.fps, fps, m.channels))
            names.append(Path(f).stem)
        if ch is None:
            raise DataError("no training files given")
        return TrainingSet(seqs, list(ch), fps, names, [splits.ACTIVITY.get(n, "walk") for n in names], self.skeleton)


# ---- pan2009 ------------------------------------------------------------------------------------
class Pan2009(Protocol):
    name = "pan2009"
    description = "Pan & Torresani 2009 s4.3: 07_01, second half, all but the 14 leg channels erased"
    TRAIN = ["07_02", "07_09", "07_10"] + datasets.SUBJECT35_WALKS + datasets.SUBJECT35_RUNS
    TEST = ["07_01"]
    options = {"fps": 120.0, "cycle_frames": 140}

    def __init__(self, split: str | None = None, train_split: bool = False):
        if split not in (None, "validation", "test"):
            raise ValueError(f"pan2009 scores the paper's test, or the walks of --split validation|test (got {split!r})")
        self.split = split
        self.train_split = train_split or split is not None

    def training_names(self) -> list[str]:
        """The paper's training set; with ``train_split``, minus every validation and test take."""
        if self.train_split:
            return [t for t in self.TRAIN if t in splits.TRAIN]
        return list(self.TRAIN)

    def test_names(self) -> list[str]:
        if self.split is None:
            return list(self.TEST)
        return [t for t in splits.SPLITS[self.split] if splits.ACTIVITY.get(t) == "walk"]

    def training_set(self) -> TrainingSet:
        return named_training_set(self.training_names())

    def cases(self, test_files: str | list[str] | None = None, asf: str | None = None) -> list[Case]:
        ch = load_take(self.TEST[0]).channels
        motions = self._load_files(test_files, asf, 120.0, ch) or [load_take(t) for t in self.test_names()]
        out = []
        for m in motions:
            T, C = m.frames.shape
            b = self.binding(m)
            keep = b.mask("legs", "pan2009")
            b.mask(["root", "upper-body"], "pan2009")  # something to erase
            obs = np.ones((T, C), bool)
            obs[T // 2 :, ~keep] = False
            rot = np.array([is_angle(c) for c in m.channels]) & ~keep
            out.append(Case(Path(m.source).stem, "all-but-legs", m.frames, obs, m.channels, m.fps, rot,
                            {"first_erased": T // 2, "cm_per_unit": _cm_per_unit(m, b), **_skeleton_info(b, m.skeleton)}))
        return out

    def score(self, case: Case, filled: np.ndarray) -> list[dict[str, Any]]:
        err = wrapped_error(case, filled)
        t0 = case.info["first_erased"]
        e = err[t0:, case.scored]
        trans = np.array([c in case.info.get("root_translation", ("root.tx", "root.ty", "root.tz"))
                          for c in case.channels])
        et = err[t0:, trans]
        return [
            _row(case, "mse_deg2", np.mean(e**2)),
            _row(case, "rms_deg", np.sqrt(np.mean(e**2))),
            _row(case, "root_translation_mse", np.mean(et**2)),
        ]


# ---- taylor2007 ---------------------------------------------------------------------------------
def _taylor_mat(root: Path | None = None) -> dict[str, np.ndarray]:
    import scipy.io

    root = root or datasets.data_dir(required=True)
    p = Path(root) / "cmu35_taylor" / "cmu35WalkJog.mat"
    if not p.exists():
        raise DataError(f"taylor2007 split not found at {p}")
    return scipy.io.loadmat(str(p))


def _split_by_labels(Y: np.ndarray, lbls: np.ndarray) -> list[np.ndarray]:
    idx = lbls.argmax(1)
    return [Y[idx == k] for k in range(lbls.shape[1]) if (idx == k).any()]


def taylor_skeleton() -> Any:
    """Subject 35's ASF: Taylor's arrays are its AMC channels."""
    from mocap.asf import read_asf

    return read_asf(Path(datasets.data_dir(required=True)) / "cmu" / "35" / "35.asf")


def taylor_channels() -> list[str]:
    return taylor_skeleton().channels


class Taylor2007(Protocol):
    name = "taylor2007"
    description = "Taylor et al. 2006 s5: 35_29 walk and 35_18 jog at 30 Hz, right leg or upper body from the middle"
    TEST_NAMES = ["35_18", "35_29"]  # column order of lblstest
    options = {"fps": 30.0, "cycle_frames": 35}

    def training_set(self) -> TrainingSet:
        m = _taylor_mat()
        seqs = _split_by_labels(np.asarray(m["Y"], dtype=np.float64), m["lbls"])
        labels = ["run" if s.shape[0] < 60 else "walk" for s in seqs]
        return TrainingSet(seqs, taylor_channels(), 30.0, [f"train{k:02d}" for k in range(len(seqs))], labels)

    def train_variance(self) -> np.ndarray:
        ts = self.training_set()
        allf = np.vstack(ts.sequences)
        ang = np.array([is_angle(c) for c in ts.channels])
        v = allf.var(0)
        # angles: variance about the circular mean, so a channel near +-180 is not inflated
        from mocap.representation import circular_mean_deg

        va = np.mean(wrap180(allf - circular_mean_deg(allf))**2, 0)
        return np.where(ang, va, v)

    def patterns(self, channels: list[str], var: np.ndarray | None = None, source: str = "") -> dict[str, np.ndarray]:
        """Erasure masks over ``channels``: the right leg, and the upper body (torso, head and
        neck, arms: CMU ASF's channels from lowerback on), less constant channels."""
        var = self.train_variance() if var is None else var
        const = var < 1e-10
        b = skelmap.Binding.of(channels, self.skeleton, source)
        return {
            # constant channels are left out of both (CMU BVH's RHipJoint; CMU ASF's right leg has none)
            "right-leg": b.mask("right-leg", "taylor2007") & ~const,
            "upper-body": b.mask("upper-body", "taylor2007") & ~const,
        }

    def cases(self, test_files: str | list[str] | None = None, asf: str | None = None) -> list[Case]:
        from mocap.asf import read_asf

        ch = taylor_channels()
        files = _as_list(test_files)
        if files:
            tests = [(Path(f).stem, m, _cm_per_unit(m, self.binding(m)))
                     for f, m in zip(files, self._load_files(files, asf, 30.0, ch))]
        else:
            mat = _taylor_mat()
            seqs = _split_by_labels(np.asarray(mat["Ytest"], dtype=np.float64), mat["lblstest"])
            # Taylor's arrays are subject 35's AMC channels: that ASF's length unit
            unit = cm_per_unit(read_asf(Path(datasets.data_dir(required=True)) / "cmu" / "35" / "35.asf"))
            tests = [(n, Motion(f, ch, 30.0), unit) for n, f in zip(self.TEST_NAMES, seqs)]
        var = self.train_variance()
        out = []
        for name, m, unit in tests:
            frames, mch = m.frames, m.channels
            # another skeleton's take: scaled by its own variance (the training set is CMU ASF's)
            # (a channel moving less than CONST_TOL, 0.01 degree, counts as constant: left out)
            v = var if mch == ch else np.where(np.std(frames, 0) < CONST_TOL, 0.0, np.var(frames, 0))
            skel = m.skeleton if m.skeleton is not None else taylor_skeleton()
            T = frames.shape[0]
            for pname, mask in self.patterns(mch, v, m.source).items():
                obs = np.ones(frames.shape, bool)
                obs[T // 2 :, mask] = False
                out.append(Case(name, pname, frames, obs, mch, m.fps, mask,
                                {"first_erased": T // 2, "var": v, "cm_per_unit": unit,
                                 **_skeleton_info(skelmap.Binding.of(mch, self.skeleton, m.source), skel)}))
        return out

    def score(self, case: Case, filled: np.ndarray) -> list[dict[str, Any]]:
        err = wrapped_error(case, filled)
        t0 = case.info["first_erased"]
        e = err[t0:, case.scored]
        var = case.info["var"][case.scored]
        cum = np.mean(np.sum(e**2, 0) / var)
        return [_row(case, "cumulative_scaled_error", cum), _row(case, "rms_deg", np.sqrt(np.mean(e**2)))]


# ---- gaps ---------------------------------------------------------------------------------------
class Gaps(Protocol):
    name = "gaps"
    description = ("seeded bursts of dropout (0.1-2 s) on joint groups and the root, several at once; "
                   "trained on splits.TRAIN, scored on splits.VALIDATION (default) or TEST")
    options = {"fps": 120.0, "cycle_frames": 140}
    RATE_PER_GROUP = 0.6  # bursts per second per joint group
    CLEAN_LEAD = 0.25  # seconds at the start with every marker present

    def __init__(self, seed: int = 0, split: str = "validation"):
        if split not in ("validation", "test"):
            raise ValueError(f"gaps scores --split validation or test (got {split!r})")
        self.seed = seed
        self.split = split

    def training_set(self) -> TrainingSet:
        return named_training_set(list(splits.TRAIN))

    def test_names(self) -> list[str]:
        return list(splits.SPLITS[self.split])

    def occlusion(self, name: str, T: int, channels: list[str], fps: float) -> tuple[np.ndarray, list[tuple[str, int, int]]]:
        """Seeded mask (T, C) and the bursts (group, start, stop); the first CLEAN_LEAD seconds stay clean.

        The root group is drawn last, so the other groups' bursts are those of JOINT_GROUPS alone."""
        rng = np.random.default_rng([self.seed, zlib.crc32(name.encode())])
        obs = np.ones((T, len(channels)), bool)
        bursts = []
        lo, hi = GAP_BINS[0][0], GAP_BINS[-1][1]
        sk = skelmap.Binding.of(channels, self.skeleton, name)
        sk.mask(list(GAP_GROUPS), "gaps")  # a skeleton with none of the groups would erase nothing
        for g in GAP_GROUPS:
            cols = sk.mask(g, require=False)
            erase_bursts(obs, cols, g, rng, fps, self.CLEAN_LEAD, self.RATE_PER_GROUP, lo, hi, bursts)
        return obs, bursts

    def cases(self, test_files: str | list[str] | None = None, asf: str | None = None) -> list[Case]:
        ch = load_take(splits.TRAIN[0]).channels
        motions = self._load_files(test_files, asf, 120.0, ch) or [load_take(t) for t in self.test_names()]
        out = []
        for m in motions:
            name = Path(m.source).stem
            obs, bursts = self.occlusion(name, m.n_frames, m.channels, m.fps)
            scored = np.array([is_angle(c) for c in m.channels])
            b = self.binding(m)
            out.append(Case(name, "gaps", m.frames, obs, m.channels, m.fps, scored,
                            {"bursts": bursts, "seed": self.seed, "cm_per_unit": _cm_per_unit(m, b),
                             **_skeleton_info(b, m.skeleton)}))
        return out


PROTOCOLS: dict[str, Callable[[], Protocol]] = {"pan2009": Pan2009, "taylor2007": Taylor2007, "gaps": Gaps}


def get_protocol(name: str, **kw: Any) -> Protocol:
    if name not in PROTOCOLS:
        raise KeyError(f"unknown protocol {name!r} (known: {', '.join(PROTOCOLS)})")
    return PROTOCOLS[name](**kw)
