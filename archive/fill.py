"""Fill one recorded take: read it with its real gaps, erase a rehearsal pattern if asked, run
the method over the whole take, write the filled take and its sidecar atomically.

``fill_take`` is what a Dask task runs.  It is idempotent (the same inputs give the same files;
a rerun after a lost worker only replaces them) and never raises for a bad take: the error
comes back in the result, so one broken file cannot stop a batch.

Method choice (``resolve_method``): a model file's best method that may use the whole take
(``BEST_OFFLINE``: HLM's smoother, eq. 18 over the whole take; models without an offline method use their own
causal fill); ``--method hold|interp`` without a model fit those baselines on the take itself.
"""
from __future__ import annotations

import os
import tempfile
import time
import traceback
from dataclasses import dataclass
from typing import Any

import numpy as np

from archive.formats import FILL_SUFFIX, fill_sidecar, read_fill_sidecar, sha256_file
from archive.takes import TakeJob, read_with_gaps, readable, write_filled
from lacuna.errors import LacunaError
from mocap.atomic import atomic_write_text

# model file's method -> the method `lacuna fill` uses by default.  HLM: smoothing over the take
# (chosen on the VALIDATION takes, docs/ARCHIVE.md ## Choice of method); every other model
# family has only causal fills, which are used as they are.
BEST_OFFLINE = {"hlm": "hlm-offline"}
# methods that need no trained model: fitted on the take's own observed values
MODEL_FREE = ("hold", "interp")
# a model trained at one rate fills takes at that rate only (relative tolerance)
FPS_TOLERANCE = 0.01


@dataclass(frozen=True)
class FillSpec:
    """What every take of a batch is filled with."""

    method: str
    model_path: str | None = None      # the model file as named on the command line
    model_sha256: str | None = None
    model_method: str | None = None
    drop: str | None = None            # rehearsal pattern (clients.takes.drop_mask)
    seed: int = 0


def resolve_method(method: str | None, model_meta: dict[str, Any] | None) -> str:
    """The method a batch runs, or LacunaError saying why the choice is impossible."""
    from lacuna import registry

    if model_meta is None:
        if method is None:
            raise LacunaError("give --model FILE (a trained model) or --method hold|interp (fitted on each take)")
        if method not in MODEL_FREE:
            known = registry.methods()
            if method not in known:
                raise LacunaError(f"--method {method}: unknown method (known: {', '.join(known)})")
            raise LacunaError(f"--method {method} needs a trained model: pass --model FILE")
        return method
    fam = model_meta.get("method")
    if method is None:
        return BEST_OFFLINE.get(fam, fam)
    if method == fam or method.startswith(f"{fam}-") and fam == "hlm":
        registry.get_method(method)  # exists
        return method
    raise LacunaError(f"--method {method} cannot run a {fam!r} model file (its methods: "
                      f"{', '.join(sorted(m for m in registry.methods() if m == fam or m.startswith(fam + '-')) if fam == 'hlm' else [fam])})")


_MODELS: dict[str, Any] = {}    # sha256 -> loaded model, one per worker process


def model_from_bytes(sha: str, data: bytes) -> Any:
    """Load (once per process) a model file shipped as bytes."""
    if sha not in _MODELS:
        from lacuna.modelfile import load_model

        path = os.path.join(tempfile.gettempdir(), f"lacuna-model-{sha}.npz")
        if not os.path.exists(path):
            fd, tmp = tempfile.mkstemp(prefix=".lacuna-model-", suffix=".part", dir=os.path.dirname(path))
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
            os.replace(tmp, path)
        _MODELS[sha] = load_model(path)
    return _MODELS[sha]


def is_done(job: TakeJob, spec: FillSpec, model_file: str | None) -> bool:
    """True when the take's output and sidecar are complete, newer than the input and the model,
    and were made with this method, model and drop pattern (and its seed)."""
    side = read_fill_sidecar(job.output + FILL_SUFFIX)
    if side is None or not os.path.exists(job.output):
        return False
    if (side.get("method"), (side.get("model") or {}).get("sha256"), side.get("drop"), side.get("drop_seed")) != \
            (spec.method, spec.model_sha256, spec.drop, spec.seed if spec.drop else None):
        return False
    t_out = os.path.getmtime(job.output)
    newer = [job.source] + ([model_file] if model_file else [])
    return all(t_out >= os.path.getmtime(p) for p in newer if os.path.exists(p))


def _model_for(spec: FillSpec, model: Any, motion, known: np.ndarray):
    if model is not None:
        return model
    from mocap.baselines import HoldModel, InterpModel, _channel_stats

    # fit on the observed values only: each channel's mean and spread from its own known frames
    cols = [np.where(known[:, j], motion.frames[:, j], np.nan) for j in range(motion.frames.shape[1])]
    stats = [_channel_stats(c[np.isfinite(c)][:, None], [ch]) if np.isfinite(c).any() else (np.zeros(1), np.zeros(1))
             for c, ch in zip(cols, motion.channels)]
    mean = np.array([s[0][0] for s in stats])
    std = np.array([s[1][0] for s in stats])
    cls = InterpModel if spec.method == "interp" else HoldModel
    return cls(list(motion.channels), mean, std)


def fill_arrays(spec: FillSpec, model: Any, motion, known: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(observed, filled frames, std, held) for a take; frames (T, C) in the take's channels.

    ``observed`` = known and not erased by the rehearsal pattern.  Channels the model lacks are
    held from their last observed value (``held``) so every written value is finite.
    """
    from clients.replay import _hold_forward
    from clients.takes import drop_mask
    from lacuna.registry import get_method

    T, C = motion.frames.shape
    keep = np.ones((T, C), bool)
    if spec.drop:
        # a short take in which no burst falls is a rehearsal with nothing to fill, not a failure
        keep, _ = drop_mask(spec.drop, motion, spec.seed, require_erased=False)
    observed = known & keep
    m = _model_for(spec, model, motion, observed)
    mfps = (getattr(m, "meta", None) or {}).get("training", {}).get("fps")
    if mfps and abs(motion.fps - mfps) > FPS_TOLERANCE * mfps:
        raise LacunaError(f"{motion.source}: take at {motion.fps:g} Hz, the model was trained at {mfps:g} Hz")
    missing = [c for c in m.channels if c not in motion.channels]
    if missing:
        raise LacunaError(f"{motion.source}: lacks {len(missing)} of the model's channels (e.g. {', '.join(missing[:3])})")
    idx = motion.index(m.channels)
    x = np.where(observed, motion.frames, 0.0)
    f, s = get_method(spec.method).run(m, x[:, idx], observed[:, idx])
    out = np.where(observed, motion.frames, np.nan)
    std = np.zeros((T, C))
    out[:, idx] = np.where(observed[:, idx], motion.frames[:, idx], f)
    std[:, idx] = np.where(observed[:, idx], 0.0, s)
    held = ~np.isfinite(out)
    if held.any():
        out = _hold_forward(out)
    if not np.all(np.isfinite(out)) or not np.all(np.isfinite(std)):
        raise LacunaError(f"{motion.source}: the {spec.method} fill produced non-finite values")
    return observed, out, std, held


def fill_take(job: TakeJob, spec: FillSpec, model_blob: tuple[str, bytes] | None = None) -> dict[str, Any]:
    """Fill one take; returns its result row (``status`` 'filled' or 'failed', counts, timings)."""
    from archive.worker import tune_malloc

    tune_malloc()  # in a Dask worker (archive/worker.py); harmless in a plain process
    t0 = time.perf_counter()
    row: dict[str, Any] = {"index": job.index, "source": job.source, "output": job.output, "pid": os.getpid()}
    try:
        model = model_from_bytes(*model_blob) if model_blob is not None else None
        t1 = time.perf_counter()
        motion, known = read_with_gaps(job.source)
        t2 = time.perf_counter()
        observed, out, std, held = fill_arrays(spec, model, motion, known)
        t3 = time.perf_counter()
        filled = ~observed & ~held
        truth = motion.frames
        motion.frames = out
        write_filled(job.output, motion, observed, std)
        extra: dict[str, Any] = {"real_gap_values": int((~known).sum()), "held_values": int(held.sum()),
                                 "drop_seed": spec.seed if spec.drop else None}
        if spec.drop:
            from clients.replay import errors

            erased = known & ~observed
            extra["rehearsal"] = errors(np.nan_to_num(truth), out, erased, motion.channels)
        side = fill_sidecar(source=job.source, source_sha256=sha256_file(job.source), output=job.output,
                            method=spec.method, causal=_causal(spec.method),
                            model=None if spec.model_path is None else {"path": spec.model_path, "sha256": spec.model_sha256,
                                                                        "method": spec.model_method},
                            drop=spec.drop, channels=motion.channels, fps=motion.fps, filled=filled, std=std,
                            held=held, extra=extra)
        import json

        atomic_write_text(job.output + FILL_SUFFIX, json.dumps(side, separators=(",", ":")) + "\n")
        readable(job.output + FILL_SUFFIX)
        t4 = time.perf_counter()
        row.update(status="filled", frames=int(motion.n_frames), channels=len(motion.channels),
                   values_filled=int(filled.sum()), held_values=int(held.sum()), real_gap_values=extra["real_gap_values"],
                   seconds={"model": t1 - t0, "read": t2 - t1, "fill": t3 - t2, "write": t4 - t3, "total": t4 - t0})
        if spec.drop:
            row["rehearsal"] = {k: extra["rehearsal"][k] for k in ("rms_deg", "erased_values")}
    except Exception as e:  # a bad take is reported, never raised: the batch goes on
        msg = str(e) if isinstance(e, (LacunaError, ValueError, OSError, KeyError)) else \
            f"{type(e).__name__}: {e} ({traceback.format_exc(limit=-1).strip().splitlines()[-2].strip()})"
        msg = msg.strip("'\"")
        msg = msg[len(job.source) + 2:] if msg.startswith(job.source + ": ") else msg   # the row names the take
        row.update(status="failed", error=msg, seconds={"total": time.perf_counter() - t0})
    return row


def _causal(method: str) -> bool:
    from lacuna.registry import get_method

    return bool(get_method(method).causal)
