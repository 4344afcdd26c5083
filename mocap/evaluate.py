"""Run a method on a protocol: train (or load), fill every case, score, tabulate, plot.

The JSON written by ``lacuna eval --json`` is
``{"protocol", "method", "causal", "model", "train_seconds", "results": [{"test", "erased", "metric", "value"}]}``.
"""
from __future__ import annotations

import json
import sys
import time
from typing import Any

import numpy as np

from lacuna import modelfile, registry
from mocap.protocols import Case, Protocol, get_protocol


def _progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def run_cases(protocol: Protocol, spec: registry.MethodSpec, model: Any, cases: list[Case],
              progress: bool = True) -> tuple[list[dict[str, Any]], list[np.ndarray]]:
    rows, fills = [], []
    for i, case in enumerate(cases):
        if progress:
            _progress(f"  [{i + 1}/{len(cases)}] {spec.name} on {case.test} ({case.erased}, {case.truth.shape[0]} frames)")
        given = np.where(case.observed, case.truth, np.nan)
        filled, _std = spec.run(model, given, case.observed.copy())
        fills.append(filled)
        rows += protocol.score(case, filled)
    return rows, fills


def evaluate(protocol_name: str, method: str, model_path: str | None = None, test_file: str | None = None,
             asf: str | None = None, options: dict[str, Any] | None = None, progress: bool = True,
             seed: int = 0) -> dict[str, Any]:
    """Train (or load) ``method``, fill the protocol's cases, and score them."""
    protocol = get_protocol(protocol_name, **({"seed": seed} if protocol_name == "gaps" else {}))
    spec = registry.get_method(method)
    t0 = time.perf_counter()
    if model_path:
        model = modelfile.load_model(model_path)
        train_seconds = None
    else:
        if progress:
            _progress(f"training {method} on the {protocol_name} training set ...")
        ts = protocol.training_set()
        opts = {**protocol.options, **spec.defaults, **(options or {})}
        model = spec.train(ts, **opts)
        train_seconds = time.perf_counter() - t0
    cases = protocol.cases(test_file=test_file, asf=asf)
    if list(model.channels) != list(cases[0].channels):
        raise ValueError(f"model channels ({len(model.channels)}) do not match the protocol's ({len(cases[0].channels)})")
    rows, fills = run_cases(protocol, spec, model, cases, progress)
    return {
        "protocol": protocol_name,
        "method": method,
        "causal": spec.causal,
        "model": model_path,
        "train_seconds": train_seconds,
        "results": rows,
        "_cases": cases,
        "_fills": fills,
        "_protocol": protocol,
    }


def public(result: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in result.items() if not k.startswith("_")}


def format_table(result: dict[str, Any]) -> str:
    rows = result["results"]
    head = f"protocol {result['protocol']}  method {result['method']}" + ("" if result["causal"] else "  (offline: not causal)")
    if result.get("train_seconds") is not None:
        head += f"  trained in {result['train_seconds']:.1f} s"
    w = [max(len(str(r[k])) for r in rows + [{"test": "test", "erased": "erased", "metric": "metric"}]) for k in ("test", "erased", "metric")]
    lines = [head, f"{'test':<{w[0]}}  {'erased':<{w[1]}}  {'metric':<{w[2]}}  value"]
    for r in rows:
        lines.append(f"{r['test']:<{w[0]}}  {r['erased']:<{w[1]}}  {r['metric']:<{w[2]}}  {r['value']:.3f}")
    return "\n".join(lines)


def write_json(result: dict[str, Any], path: str) -> None:
    with open(path, "w") as fh:
        json.dump(public(result), fh, indent=2)
        fh.write("\n")


def plot(result: dict[str, Any], path: str, reference: str = "nn", max_channels: int = 4) -> None:
    """Truth, fill and the nearest-neighbour fill for a few erased channels of each case
    (like the papers' figures)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    protocol: Protocol = result["_protocol"]
    cases: list[Case] = result["_cases"]
    fills = result["_fills"]
    ref_fills = None
    if reference and reference != result["method"]:
        spec = registry.get_method(reference)
        ref_model = spec.train(protocol.training_set())
        _, ref_fills = run_cases(protocol, spec, ref_model, cases, progress=False)
    fig, axes = plt.subplots(len(cases), max_channels, figsize=(4 * max_channels, 2.6 * len(cases)), squeeze=False)
    for i, case in enumerate(cases):
        miss = case.missing & case.scored[None, :]
        cols = np.flatnonzero(miss.any(0))
        # the channels that move most are the informative ones to look at
        cols = cols[np.argsort(-case.truth[:, cols].std(0))][:max_channels]
        t = np.arange(case.truth.shape[0]) / case.fps
        for j in range(max_channels):
            ax = axes[i, j]
            if j >= len(cols):
                ax.axis("off")
                continue
            c = cols[j]
            ax.plot(t, case.truth[:, c], "k-", lw=1.4, label="truth")
            m = miss[:, c]
            fill = np.where(m, fills[i][:, c], np.nan)
            ax.plot(t, fill, "r--", lw=1.3, label=result["method"])
            if ref_fills is not None:
                ax.plot(t, np.where(m, ref_fills[i][:, c], np.nan), "b:", lw=1.2, label=reference)
            ax.axvspan(t[m.argmax()] if m.any() else 0, t[-1], color="0.92", zorder=0)
            ax.set_title(f"{case.test} {case.erased}: {case.channels[c]}", fontsize=8)
            ax.tick_params(labelsize=7)
            if i == 0 and j == 0:
                ax.legend(fontsize=7)
    fig.suptitle(f"{result['protocol']}: {result['method']} (grey = erased)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
