"""Model files: one ``.npz`` of named arrays plus a JSON metadata string.  Never pickle.

Layout inside the npz:
  ``__meta__``   0-d unicode array holding JSON: {"format": "lacuna-model", "format_version": 1,
                 "method": "hlm"|"crbm"|"nn"|..., "channels": [...], "representation": {...},
                 "hyperparameters": {...}, "training": {"data": [...], "seconds": ..., "date": ...},
                 ...anything else the method needs}
  other keys     float/int/bool arrays, validated for shape and finiteness by the loader.

``load_model(path)`` reads the metadata, looks up the method in the registry and calls its
``from_arrays(meta, arrays)``; every failure is a ModelFileError naming the file and the cause.
"""
from __future__ import annotations

import datetime as _dt
import io
import json
import os
import zipfile
from collections.abc import Callable
from typing import Any

import numpy as np

FORMAT = "lacuna-model"
FORMAT_VERSION = 1


class ModelFileError(ValueError):
    """A model file that cannot be used: missing, truncated, wrong format, bad shapes."""


def save_arrays(path: str | os.PathLike, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
    """Write atomically (temp file + rename) so a reader never sees half a model."""
    meta = dict(meta)
    meta.setdefault("format", FORMAT)
    meta.setdefault("format_version", FORMAT_VERSION)
    meta.setdefault("saved", _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"))
    for k, v in arrays.items():
        if k == "__meta__":
            raise ValueError("array name __meta__ is reserved")
        a = np.asarray(v)
        if a.dtype == object:
            raise ValueError(f"array {k!r} has dtype object; model files hold plain arrays only")
    path = os.fspath(path)
    tmp = f"{path}.tmp{os.getpid()}"
    buf = io.BytesIO()
    np.savez_compressed(buf, __meta__=np.array(json.dumps(meta, sort_keys=True)), **{k: np.asarray(v) for k, v in arrays.items()})  # type: ignore[arg-type]
    with open(tmp, "wb") as fh:
        fh.write(buf.getvalue())
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def load_arrays(path: str | os.PathLike) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Read and check the container; returns (meta, arrays).  Raises ModelFileError."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError as e:
        raise ModelFileError(f"{path}: cannot read model file ({e.strerror or e})") from None
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError) as e:
        raise ModelFileError(f"{path}: not a readable model file (truncated or corrupt: {e})") from None
    except Exception as e:  # zlib.error, struct.error, MemoryError...: corrupt bytes raise assorted errors
        raise ModelFileError(f"{path}: not a readable model file (truncated or corrupt: {type(e).__name__}: {e})") from None
    if "__meta__" not in arrays:
        raise ModelFileError(f"{path}: no __meta__ entry; not a lacuna model file")
    try:
        meta = json.loads(str(arrays.pop("__meta__")))
    except json.JSONDecodeError as e:
        raise ModelFileError(f"{path}: metadata is not valid JSON ({e})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ModelFileError(f"{path}: metadata format is {meta.get('format') if isinstance(meta, dict) else meta!r}, expected {FORMAT!r}")
    ver = meta.get("format_version")
    if ver != FORMAT_VERSION:
        raise ModelFileError(f"{path}: format_version {ver!r} is not supported (this lacuna reads {FORMAT_VERSION})")
    if not isinstance(meta.get("channels"), list) or not all(isinstance(c, str) for c in meta["channels"]):
        raise ModelFileError(f"{path}: metadata 'channels' must be a list of channel names")
    for k, a in arrays.items():
        if a.dtype.kind not in "biuf":  # complex, strings, void...: no model stores those
            raise ModelFileError(f"{path}: array {k!r} has dtype {a.dtype}; model files hold real numbers and booleans")
        if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            raise ModelFileError(f"{path}: array {k!r} holds NaN or infinity")
    return meta, arrays


def require(path: str, arrays: dict[str, np.ndarray], name: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """Fetch an array and check its shape (None = any size on that axis)."""
    if name not in arrays:
        raise ModelFileError(f"{path}: missing array {name!r}")
    a = arrays[name]
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        raise ModelFileError(f"{path}: array {name!r} has shape {a.shape}, expected {tuple('*' if s is None else s for s in shape)}")
    return a


# ---- registry of loadable methods -------------------------------------------------------------
_LOADERS: dict[str, Callable[[str, dict[str, Any], dict[str, np.ndarray]], Any]] = {}


def register_loader(method: str, loader: Callable[[str, dict[str, Any], dict[str, np.ndarray]], Any]) -> None:
    """``loader(path, meta, arrays) -> Model``; it raises ModelFileError on bad shapes."""
    _LOADERS[method] = loader


def load_model(path: str | os.PathLike):
    """Load any lacuna model file, dispatching on its ``method``."""
    from lacuna import registry  # noqa: F401  (imports the method modules, which register loaders)

    path = os.fspath(path)
    meta, arrays = load_arrays(path)
    method = meta.get("method")
    registry.ensure_loaded()
    if method not in _LOADERS:
        raise ModelFileError(f"{path}: unknown method {method!r} (known: {sorted(_LOADERS)})")
    try:
        return _LOADERS[method](path, meta, arrays)
    except ModelFileError:
        raise
    except (KeyError, ValueError, TypeError, IndexError) as e:
        raise ModelFileError(f"{path}: {method} model is malformed ({type(e).__name__}: {e})") from None
