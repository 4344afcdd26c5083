"""Where motion data lives and how to load a named trial.

Data directory: ``$LACUNA_DATA``, else ``../shared/data`` beside a development checkout (found
by walking up from the current directory and from this package), else the per-user cache
(``$XDG_CACHE_HOME/lacuna/data`` or ``~/.cache/lacuna/data``) that ``lacuna data fetch`` fills.
The layout is CMU's: ``cmu/<subject>/<subject>.asf`` and ``cmu/<subject>/<subject>_<trial>.amc``.
"""
from __future__ import annotations

import os
from pathlib import Path

from lacuna.errors import DataError
from mocap.motion import Motion


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "lacuna" / "data"


def _shared_candidates() -> list[Path]:
    out = []
    for start in (Path.cwd(), Path(__file__).resolve().parent):
        for d in [start, *start.parents]:
            out.append(d.parent / "shared" / "data" if d.name else d / "shared" / "data")
            out.append(d / "../shared/data")
    return out


def data_dir(required: bool = False) -> Path | None:
    """The data directory in use, or None (or DataError when ``required``)."""
    env = os.environ.get("LACUNA_DATA")
    if env:
        p = Path(env)
        if not p.is_dir():
            raise DataError(f"LACUNA_DATA={env} is not a directory")
        return p
    for cand in _shared_candidates():
        if (cand / "cmu").is_dir():
            return cand.resolve()
    c = cache_dir()
    if (c / "cmu").is_dir():
        return c
    if required:
        raise DataError(
            "no motion data found: set LACUNA_DATA, work beside ../shared/data, "
            "or run `lacuna data fetch cmu --subjects 07 35`"
        )
    return None


def trial_path(trial: str, root: Path | None = None) -> Path:
    """``"07_01"`` -> ``<data>/cmu/07/07_01.amc`` (DataError naming the path if absent)."""
    root = root or data_dir(required=True)
    subj = trial.split("_")[0]
    p = Path(root) / "cmu" / subj / f"{trial}.amc"
    if not p.exists():
        raise DataError(f"trial {trial} not found at {p} (try `lacuna data fetch cmu --subjects {subj}`)")
    return p


def load_trial(trial: str, root: Path | None = None) -> Motion:
    """Load a CMU trial by name, e.g. ``load_trial("35_29")``; 120 Hz, 62 channels, degrees."""
    from mocap.asf import read_amc

    return read_amc(trial_path(trial, root))


# Subject-35 trials in the data set, by CMU's motion label.
SUBJECT35_WALKS = ["35_01"] + [f"35_{i:02d}" for i in range(6, 17)] + [f"35_{i:02d}" for i in range(28, 35)]
SUBJECT35_RUNS = ["35_17", "35_23", "35_24", "35_25"]
