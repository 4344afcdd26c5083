"""Run a method on a protocol: train once (or load), fill every case, score, aggregate, tabulate.

From Python (what ``lacuna eval`` calls; no CLI needed)::

    from mocap.evaluate import evaluate, value
    res = evaluate("gaps", "hold", split="validation", seeds=[0, 1, 2])
    value(res, "rms_deg[len 0.5-1s]", activity="walk")          # pooled over walks and seeds
    value(res, "within_2std", test="walking_20")                 # one take, pooled over seeds

To tune a method, train once and score many settings without retraining where the method
allows it: ``model = train(get_protocol("gaps"), "hlm", options)`` then
``evaluate("gaps", "hlm", model=model, seeds=[0, 1, 2])``.  ``keep=False`` drops the fills
from the result (less memory in a tuning loop).

Arguments of ``evaluate``: ``split`` "validation" (the default of ``gaps``) or "test" for gaps;
for pan2009 None (the paper's 07_01) or "validation"/"test" (that split's walks, trained without
any validation or test take); ``train_split=True`` makes pan2009 train on that reduced set for
``test_file`` too.  ``test_file`` is a path or a list of paths (one model scores every file).
``seeds`` (gaps only) lists occlusion seeds; figures pool the values of every seed.
``trained_on`` names the takes a given ``model`` saw (default: the protocol's training set; for a
``model_path``, the file's ``training.data``), so rows of those takes are flagged ``in_training``.
``fills_dir`` writes one ``<stem>[-<pattern>][-seed<k>].npz`` per case (see ``write_fill``).

Result: ``{"protocol", "method", "causal", "model", "train_seconds", "split", "seeds",
"trained_on", "std_floor_deg", "results": [row, ...]}``; each row is ``{"test", "erased",
"split", "activity", "metric", "value", "n"}`` (``value`` None where a figure is n/a, ``n`` the
number of values it pools; ``in_training`` True on a per-take row whose take the model was
trained on).  Per-take rows have the take's name in ``test``; aggregates have ``test`` "all"
and ``activity`` one of walk/turn/run/nonloco or "all".  ``split`` is the take's split
(train / validation / test / paper-test / external) or, on aggregates, the split scored.
Metric names and definitions: mocap.metrics.  The private keys ``_cases``, ``_fills``,
``_stds`` hold the arrays (not written to JSON).
"""
from __future__ import annotations

import json
import sys
import time
from collections import defaultdict
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from lacuna import modelfile, registry
from mocap import metrics, skelmap, splits
from mocap.protocols import GAP_GROUPS, Case, Protocol, get_protocol

ACTIVITIES = ("walk", "turn", "run", "nonloco")


def _progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def make_protocol(name: str, seed: int = 0, split: str | None = None, train_split: bool = False) -> Protocol:
    """The protocol object for ``evaluate``'s arguments (ValueError on a combination it lacks)."""
    if name == "gaps":
        return get_protocol("gaps", seed=seed, split=split or "validation")
    if name == "pan2009":
        return get_protocol("pan2009", split=split, train_split=train_split)
    if split or train_split:
        raise ValueError(f"{name} has its own training and test split (no --split / --train-split)")
    return get_protocol(name)


def train(protocol: Protocol, method: str, options: dict[str, Any] | None = None, progress: bool = True,
          train_files: list[str] | None = None, asf: str | None = None) -> Any:
    """Train ``method`` on the protocol's training set (or on ``train_files``, takes of any
    skeleton: ``Protocol.files_training_set``) with its options and the method's defaults."""
    spec = registry.get_method(method)
    if progress:
        what = f"{len(train_files)} files" if train_files else f"the {protocol.name} training set"
        _progress(f"training {method} on {what} ...")
    opts = {**protocol.options, **spec.defaults, **(options or {})}
    ts = protocol.files_training_set(train_files, asf) if train_files else protocol.training_set()
    return spec.train(ts, **opts)


def activity_of(take: str) -> str:
    return splits.ACTIVITY.get(take, "unknown")


def split_label(take: str) -> str:
    return splits.split_of(take) or "external"


def fill_name(case: Case, several_patterns: bool, several_seeds: bool) -> str:
    name = case.test + (f"-{case.erased}" if several_patterns else "")
    return name + (f"-seed{case.info['seed']}" if several_seeds else "")


def write_fill(path: Path, case: Case, filled: np.ndarray, std: np.ndarray) -> None:
    """``truth``, ``fill``, ``std`` (T, C; degrees, the file's length unit for root translation),
    ``erased`` (T, C bool), ``channels``, ``fps`` (and ``scored``, ``seed`` where there is one)."""
    import io

    from mocap.atomic import atomic_write_bytes

    buf = io.BytesIO()
    np.savez_compressed(buf, truth=np.asarray(case.truth, np.float64), fill=np.asarray(filled, np.float64),
                        std=np.asarray(std, np.float64), erased=~np.asarray(case.observed, bool),
                        channels=np.array(case.channels), fps=np.float64(case.fps),
                        scored=np.asarray(case.scored, bool), seed=np.int64(case.info.get("seed", -1)))
    atomic_write_bytes(path, buf.getvalue())


def evaluate(protocol_name: str, method: str, model_path: str | None = None,
             test_file: str | list[str] | None = None, asf: str | None = None,
             options: dict[str, Any] | None = None, progress: bool = True, seed: int = 0, *,
             seeds: Iterable[int] | None = None, split: str | None = None, train_split: bool = False,
             model: Any = None, fills_dir: str | None = None, keep: bool = True,
             trained_on: list[str] | None = None, skeleton: str | None = None,
             train_files: list[str] | None = None) -> dict[str, Any]:
    """Train (or load, or take ``model``) once, fill every case of every seed, score and aggregate.
    ``skeleton``: the skeleton map of the test files (name or file; default recognised).
    ``train_files``: train on these takes instead of the protocol's training set (BVH takes for
    BVH test files)."""
    seeds = [int(s) for s in seeds] if seeds is not None else [int(seed)]
    if not seeds:
        raise ValueError("no seeds given")
    if protocol_name != "gaps" and seeds != [0]:
        raise ValueError(f"{protocol_name} erases the same values every time: seeds apply to the gaps protocol only")
    protocols = [make_protocol(protocol_name, s, split, train_split) for s in seeds]
    for p in protocols:
        p.skeleton = skeleton
    spec = registry.get_method(method)
    # the cases first: a bad --test file fails before minutes of training
    case_lists = [proto.cases(test_files=test_file, asf=asf) for proto in protocols]
    t0 = time.perf_counter()
    train_seconds = None
    if model is None and model_path:
        model = modelfile.load_model(model_path)
    elif model is None:
        model = train(protocols[0], method, options, progress, train_files, asf)
        train_seconds = time.perf_counter() - t0
    if trained_on is None:
        if model_path:  # what the file says it was trained on (HLM and CRBM files say; others: unknown)
            meta, _ = modelfile.load_arrays(model_path)
            trained_on = list((meta.get("training") or {}).get("data") or [])
        elif train_files:
            trained_on = [Path(f).stem for f in train_files]
        else:
            trained_on = list(protocols[0].training_set().names)
    seen = set(trained_on)

    per_case: list[tuple[Case, metrics.Values, list[dict[str, Any]]]] = []
    cases_all, fills_all, stds_all = [], [], []
    for proto, cases in zip(protocols, case_lists):
        if list(model.channels) != list(cases[0].channels):
            why = skelmap.mismatch(model.channels, cases[0].channels, cases[0].test, skeleton,
                                   str(getattr(model, "meta", {}).get("skeleton_map") or "")) if test_file else None
            if why:
                raise ValueError(why)
            raise ValueError(f"model channels ({len(model.channels)}) do not match the protocol's ({len(cases[0].channels)})"
                             + ("; the protocols train on CMU ASF takes: for takes of another skeleton train a model "
                                "on that skeleton (lacuna train hlm TAKE.bvh ...) and pass --model" if test_file else ""))
        patterns_per_take = max(sum(c.test == k.test for c in cases) for k in cases)
        for i, case in enumerate(cases):
            if progress:
                sd = f" seed {case.info['seed']}" if "seed" in case.info else ""
                _progress(f"  [{i + 1}/{len(cases)}{sd}] {spec.name} on {case.test} ({case.erased}, "
                          f"{case.truth.shape[0]} frames)")
            given = np.where(case.observed, case.truth, np.nan)
            filled, std = spec.run(model, given, case.observed.copy())
            std = np.zeros_like(filled) if std is None else np.asarray(std, np.float64)
            per_case.append((case, metrics.values(case, filled, std, case.info.get("groups", GAP_GROUPS)), proto.score(case, filled)))
            if fills_dir:
                d = Path(fills_dir)
                d.mkdir(parents=True, exist_ok=True)
                write_fill(d / f"{fill_name(case, patterns_per_take > 1, len(seeds) > 1)}.npz", case, filled, std)
            if keep:
                cases_all.append(case)
                fills_all.append(filled)
                stds_all.append(std)

    scope = "files" if test_file else (getattr(protocols[0], "split", None) or "paper-test")
    rows = aggregate(per_case, scope, seen)
    return {
        "protocol": protocol_name, "method": method, "causal": spec.causal, "model": model_path,
        "train_seconds": train_seconds, "split": scope, "seeds": seeds if protocol_name == "gaps" else None,
        "trained_on": trained_on, "std_floor_deg": metrics.STD_FLOOR, "results": rows,
        "_cases": cases_all, "_fills": fills_all, "_stds": stds_all, "_protocol": protocols[0],
    }


def _rows(test: str, erased: str, split: str, activity: str, figures, protocol_rows=()) -> list[dict[str, Any]]:
    out, have = [], set()
    for r in protocol_rows:
        out.append({"test": test, "erased": erased, "split": split, "activity": activity, "metric": r[0],
                    "value": r[1], "n": r[2]})
        have.add(r[0])
    for name, v, n in figures:
        if name not in have:  # the protocol's own figure of that name (the same number) stays
            out.append({"test": test, "erased": erased, "split": split, "activity": activity, "metric": name,
                        "value": v, "n": n})
    return out


def aggregate(per_case, scope: str, seen: set[str]) -> list[dict[str, Any]]:
    """Rows per (take, pattern) pooled over seeds, then per activity and over all takes."""
    by_take: dict[tuple[str, str], list] = defaultdict(list)
    for case, vals, prow in per_case:
        by_take[(case.test, case.erased)].append((vals, prow))
    rows: list[dict[str, Any]] = []
    for (test, erased), items in by_take.items():
        prot: dict[str, list[float]] = defaultdict(list)
        for _, pr in items:
            for r in pr:
                prot[r["metric"]].append(r["value"])
        prow = [(k, float(np.mean(v)), len(v)) for k, v in prot.items()]  # mean over seeds
        figs = metrics.summarise(metrics.Values.concat([v for v, _ in items]))
        take_rows = _rows(test, erased, split_label(test), activity_of(test), figs, prow)
        for r in take_rows:
            r["in_training"] = test in seen
        rows += take_rows
    for erased in dict.fromkeys(e for _, e in by_take):
        groups: dict[str, list] = defaultdict(list)
        for (test, e), items in by_take.items():
            if e == erased:
                groups[activity_of(test)] += [v for v, _ in items]
                groups["all"] += [v for v, _ in items]
        for act in [a for a in (*ACTIVITIES, "unknown", "all") if a in groups]:
            rows += _rows("all", erased, scope, act, metrics.summarise(metrics.Values.concat(groups[act])))
    return rows


def value(result: dict[str, Any], metric: str, test: str = "all", activity: str | None = None,
          erased: str | None = None) -> float | None:
    """One figure of an ``evaluate`` result (KeyError naming it when absent)."""
    act = activity if activity is not None else ("all" if test == "all" else None)
    hits = [r for r in result["results"] if r["metric"] == metric and r["test"] == test
            and (act is None or r["activity"] == act) and (erased is None or r["erased"] == erased)]
    if len(hits) != 1:
        raise KeyError(f"{len(hits)} rows for metric {metric!r}, test {test!r}, activity {act!r}, erased {erased!r}")
    return hits[0]["value"]


def public(result: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in result.items() if not k.startswith("_")}


def write_json(result: dict[str, Any], path: str) -> None:
    with open(path, "w") as fh:
        json.dump(public(result), fh, indent=2)
        fh.write("\n")


from mocap.evalreport import format_table, plot  # noqa: E402  (the printed table and the figure)

__all__ = ["evaluate", "train", "value", "make_protocol", "aggregate", "write_fill", "write_json", "public",
           "format_table", "plot"]
