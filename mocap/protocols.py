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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from lacuna.errors import DataError
from mocap import datasets, splits
from mocap.metrics import cm_per_unit
from mocap.motion import Motion
from mocap.representation import is_angle, resample, wrap180

LEG_BONES = ("lfemur", "ltibia", "lfoot", "ltoes", "rfemur", "rtibia", "rfoot", "rtoes")
RIGHT_LEG = ("rfemur", "rtibia", "rfoot", "rtoes")
JOINT_GROUPS = {
    "left-arm": ("lclavicle", "lhumerus", "lradius", "lwrist", "lhand", "lfingers", "lthumb"),
    "right-arm": ("rclavicle", "rhumerus", "rradius", "rwrist", "rhand", "rfingers", "rthumb"),
    "left-leg": ("lfemur", "ltibia", "lfoot", "ltoes"),
    "right-leg": ("rfemur", "rtibia", "rfoot", "rtoes"),
    "head-neck": ("lowerneck", "upperneck", "head"),
    "torso": ("lowerback", "upperback", "thorax"),
}
# the gaps protocol also drops the root (pelvis markers occluded: its rotation and translation)
GAP_GROUPS = {**JOINT_GROUPS, "root": ("root",)}
GAP_BINS = ((0.1, 0.25), (0.25, 0.5), (0.5, 1.0), (1.0, 2.0))


@functools.lru_cache(maxsize=None)
def load_take(name: str) -> Motion:
    """A named take (``splits.load_take``), parsed once per process; its frames are read-only."""
    m = splits.load_take(name)
    m.frames.flags.writeable = False
    return m


def _as_list(test_files: str | list[str] | None) -> list[str]:
    if test_files is None:
        return []
    return [test_files] if isinstance(test_files, (str, Path)) else [str(f) for f in test_files]


def _training_set(names: list[str]) -> TrainingSet:
    ms = [load_take(t) for t in names]
    labels = [splits.ACTIVITY.get(t, "walk") for t in names]
    return TrainingSet([m.frames for m in ms], ms[0].channels, 120.0, list(names), labels)


def bone(ch: str) -> str:
    return ch.split(".", 1)[0]


@dataclass
class TrainingSet:
    """sequences: list of (n_frames, n_channels) raw frames (degrees), all on ``channels``."""

    sequences: list[np.ndarray]
    channels: list[str]
    fps: float
    names: list[str]
    labels: list[str] = field(default_factory=list)

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

        p = str(path)
        if not Path(p).is_file():
            raise DataError(f"{p}: no such file")
        m = read_motion(p, asf=asf)
        missing = [c for c in channels if c not in m.channels]
        if missing:
            raise DataError(f"{p}: lacks channels the protocol needs, e.g. {missing[:3]}")
        frames = m.frames[:, m.index(channels)]
        if abs(m.fps - fps) > 1e-6:
            frames = resample(frames, m.fps, fps, channels)
        return Motion(frames, list(channels), fps, m.skeleton, p)

    def _load_files(self, test_files, asf: str | None, fps: float, channels: list[str]) -> list[Motion]:
        return [self._load_file(f, asf, fps, channels) for f in _as_list(test_files)]


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
        return _training_set(self.training_names())

    def cases(self, test_files: str | list[str] | None = None, asf: str | None = None) -> list[Case]:
        ch = load_take(self.TEST[0]).channels
        motions = self._load_files(test_files, asf, 120.0, ch) or [load_take(t) for t in self.test_names()]
        out = []
        for m in motions:
            T, C = m.frames.shape
            keep = np.array([bone(c) in LEG_BONES for c in m.channels])
            obs = np.ones((T, C), bool)
            obs[T // 2 :, ~keep] = False
            rot = np.array([is_angle(c) for c in m.channels]) & ~keep
            out.append(Case(Path(m.source).stem, "all-but-legs", m.frames, obs, m.channels, m.fps, rot,
                            {"first_erased": T // 2, "cm_per_unit": cm_per_unit(m.skeleton)}))
        return out

    def score(self, case: Case, filled: np.ndarray) -> list[dict[str, Any]]:
        err = wrapped_error(case, filled)
        t0 = case.info["first_erased"]
        e = err[t0:, case.scored]
        trans = np.array([c in ("root.tx", "root.ty", "root.tz") for c in case.channels])
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


def taylor_channels() -> list[str]:
    from mocap.asf import read_asf

    return read_asf(Path(datasets.data_dir(required=True)) / "cmu" / "35" / "35.asf").channels


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

    def patterns(self, channels: list[str]) -> dict[str, np.ndarray]:
        var = self.train_variance()
        const = var < 1e-10
        order = [bone(c) for c in channels]
        first_upper = order.index("lowerback")
        upper = np.zeros(len(channels), bool)
        upper[first_upper:] = True
        return {
            "right-leg": np.array([bone(c) in RIGHT_LEG for c in channels]),
            "upper-body": upper & ~const,
        }

    def cases(self, test_files: str | list[str] | None = None, asf: str | None = None) -> list[Case]:
        from mocap.asf import read_asf

        ch = taylor_channels()
        files = _as_list(test_files)
        if files:
            tests = [(Path(f).stem, m.frames, cm_per_unit(m.skeleton))
                     for f, m in zip(files, self._load_files(files, asf, 30.0, ch))]
        else:
            mat = _taylor_mat()
            seqs = _split_by_labels(np.asarray(mat["Ytest"], dtype=np.float64), mat["lblstest"])
            # Taylor's arrays are subject 35's AMC channels: that ASF's length unit
            unit = cm_per_unit(read_asf(Path(datasets.data_dir(required=True)) / "cmu" / "35" / "35.asf"))
            tests = [(n, f, unit) for n, f in zip(self.TEST_NAMES, seqs)]
        var = self.train_variance()
        out = []
        for name, frames, unit in tests:
            T = frames.shape[0]
            for pname, mask in self.patterns(ch).items():
                obs = np.ones(frames.shape, bool)
                obs[T // 2 :, mask] = False
                out.append(Case(name, pname, frames, obs, ch, 30.0, mask,
                                {"first_erased": T // 2, "var": var, "cm_per_unit": unit}))
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
        return _training_set(list(splits.TRAIN))

    def test_names(self) -> list[str]:
        return list(splits.SPLITS[self.split])

    def occlusion(self, name: str, T: int, channels: list[str], fps: float) -> tuple[np.ndarray, list[tuple[str, int, int]]]:
        """Seeded mask (T, C) and the bursts (group, start, stop); the first CLEAN_LEAD seconds stay clean.

        The root group is drawn last, so the other groups' bursts are those of JOINT_GROUPS alone."""
        rng = np.random.default_rng([self.seed, zlib.crc32(name.encode())])
        obs = np.ones((T, len(channels)), bool)
        bursts = []
        lo, hi = GAP_BINS[0][0], GAP_BINS[-1][1]
        for g, bones in GAP_GROUPS.items():
            cols = np.array([bone(c) in bones for c in channels])
            t = fps * (self.CLEAN_LEAD + rng.exponential(1.0 / self.RATE_PER_GROUP))
            while t < T:
                dur = np.exp(rng.uniform(np.log(lo), np.log(hi)))
                a, b = int(t), min(T, int(t + dur * fps))
                if b > a:
                    obs[a:b, cols] = False
                    bursts.append((g, a, b))
                t = b + fps * rng.exponential(1.0 / self.RATE_PER_GROUP)
        return obs, bursts

    def cases(self, test_files: str | list[str] | None = None, asf: str | None = None) -> list[Case]:
        ch = load_take(splits.TRAIN[0]).channels
        motions = self._load_files(test_files, asf, 120.0, ch) or [load_take(t) for t in self.test_names()]
        out = []
        for m in motions:
            name = Path(m.source).stem
            obs, bursts = self.occlusion(name, m.n_frames, m.channels, m.fps)
            scored = np.array([is_angle(c) for c in m.channels])
            out.append(Case(name, "gaps", m.frames, obs, m.channels, m.fps, scored,
                            {"bursts": bursts, "seed": self.seed, "cm_per_unit": cm_per_unit(m.skeleton)}))
        return out


PROTOCOLS: dict[str, Callable[[], Protocol]] = {"pan2009": Pan2009, "taylor2007": Taylor2007, "gaps": Gaps}


def get_protocol(name: str, **kw: Any) -> Protocol:
    if name not in PROTOCOLS:
        raise KeyError(f"unknown protocol {name!r} (known: {', '.join(PROTOCOLS)})")
    return PROTOCOLS[name](**kw)
