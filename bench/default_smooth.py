"""``default``'s smoothing (blend/withhlm.py, module doc "Smooth") on VALIDATION takes only: the
gaps protocol's bursts at --seeds on splits.VALIDATION, each setting's RMS, by gap length and time
since onset, onset figures, calibration and the steps inside gaps (mocap/metrics.py: step error,
pops beyond the truth's own step) per activity, beside hold.  One trained model (experts on
splits.TRAIN), every setting applied to it in turn (the smoothing is a run-time setting of the
mixing, not of the experts).

    OPENBLAS_NUM_THREADS=1 nice -n 19 .venv/bin/python bench/default_smooth.py --model /tmp/default_train.npz \
        --settings off:0:0 knots:1:0 k-p2t4:1:2:4 --seeds 0-2 --json bench/results/default_smooth_validation.json

A setting is NAME:KNOTS:POP[:POP_TAU[:POP_REL[:BAND_TAU[:RATE_A[:BQ]]]]] (KNOTS 0, 1 (W and S between the knots)
or s (S only); POP degrees a frame, 0 = off; POP_TAU frames; POP_REL x the fill's last step;
BAND_TAU frames, the band's low-passed share, 0 = off; RATE_A the band's rate exponent, 0 = off:
blend/withhlm.py "Rate"; BQ band_q from --band-q's fit (bench/default_band_q.py): 0 off, g with its rate
gate, u ungated, m the model file's own; blend/withhlm.py "Band q"; then [:PACE_TAU[:PACE_K[:PACE_A]]], the fill's pace,
blend/withhlm.py "Pace", 0 = off).  Per take, each setting's and hold's rms_deg are in the JSON ("takes_rms").  A model file without the rate's reference (``rate_ref``, written before it)
gets it from TRAIN as ``train_model`` computes it (blend.withhlm.rate_ref on protocols.Gaps()'s
training set), so a setting with RATE_A > 0 is what a model trained now would do.  Besides mocap.metrics' figures, the band's
kinks: over erased values from a gap's third frame on, |s[t] - 2 s[t-1] + s[t-2]| / s[t-1] of the
std s (a band that ramps or curves has none; one that steps has one at each step): the share above
10% and 25%.
Without --model it trains ``default`` on TRAIN (as `lacuna train default` does) and saves it there
(--save).  Progress per take on stderr.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lacuna.modelfile import load_model  # noqa: E402
from mocap import metrics, protocols, splits  # noqa: E402
from mocap.cli import parse_seeds  # noqa: E402

FIGS = ("rms_deg", "rms_deg[len 0.1-0.25s]", "rms_deg[len 0.5-1s]", "rms_deg[len 1-2s]", "rms_deg[since first]",
        "rms_deg[first 0.1s]", "hold_rms_deg[first 0.1s]", "onset_err_median_deg", "within_2std", "nll_per_value",
        "step_err_rms_deg", "pop_p99_deg", "pop_max_deg", "pop_over_2deg", "band_kink_over_10pct", "band_kink_over_25pct")


def seeds(spec: str) -> list[int]:
    return parse_seeds(spec, None)   # A-B or A,B,... as `lacuna eval --seeds`


def setting(spec: str) -> tuple[str, dict]:
    if spec == "file":   # the model file's own mixing settings, untouched (the only setting of its run)
        return "file", {"file": True, "bq": "0"}
    name, knots, pop, *rest = spec.split(":")
    out = {"knots": knots == "1", "std_knots": knots == "s", "pop": float(pop)}
    for key, v in zip(("pop_tau", "pop_rel", "band_tau", "rate_a"), rest):
        out[key] = float(v)
    bq = rest[4] if len(rest) > 4 else "0"
    if bq not in ("0", "g", "u", "m"):
        raise SystemExit(f"{spec}: BQ must be 0, g, u or m")
    for key, v in zip(("pace_tau", "pace_k", "pace_a"), rest[5:]):
        out[key] = float(v)
    return name, {**out, "bq": bq}


def with_settings(blend, **changes: float):
    """The blend (blend.model.DefaultModel) with other ``Settings`` values: built again (its
    regression matrices and shadow checks solved again), its arrays and weights the same."""
    from dataclasses import replace

    from blend.model import DefaultModel

    return DefaultModel(blend.channels, blend.mean_, blend.std_, blend.reg_idx, blend.mu_, blend.cov_,
                        replace(blend.settings, **changes), blend.weights, blend.meta, blend.vrms_, blend.vgain_,
                        blend.group)


def band_kinks(std: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """|s[t] - 2 s[t-1] + s[t-2]| / s[t-1] over erased values at least 3 frames into their gap."""
    miss = ~observed
    k = np.zeros(miss.shape, np.int64)
    k[0] = miss[0]
    for t in range(1, len(miss)):
        k[t] = np.where(miss[t], k[t - 1] + 1, 0)
    sel = k[2:] >= 3
    s0, s1, s2 = std[:-2][sel], std[1:-1][sel], std[2:][sel]
    ok = s1 > 1e-9
    return np.abs(s2 - 2 * s1 + s0)[ok] / s1[ok]


def hold_values(v: metrics.Values) -> metrics.Values:
    """The same values with hold's error in place of the fill's (std none, no steps)."""
    n = v.err.size
    return metrics.Values(err=v.hold_err, std=np.zeros(n), since=v.since, first=v.first, length=v.length,
                          group=v.group, hold_err=v.hold_err, onset_err=v.onset_err, onset_step=v.onset_step,
                          root_err=v.root_hold_err, root_hold_err=v.root_hold_err, root_unit=v.root_unit)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--model")
    ap.add_argument("--save", default="/tmp/default_train.npz")
    ap.add_argument("--settings", nargs="+", default=["off:0:0", "knots:1:0"])
    ap.add_argument("--seeds", default="0-2")
    ap.add_argument("--split", default="validation", choices=["validation", "test"])
    ap.add_argument("--json")
    ap.add_argument("--band-q", help="bench/default_band_q.py's fit (JSON), for settings with BQ g or u")
    ap.add_argument("--gate-n0", type=float, help="the blend's gate_n0 instead of the file's (blend/model.py Settings)")
    ap.add_argument("--blend-setting", action="append", default=[], metavar="KEY=VALUE",
                    help="a blend/model.py Settings value instead of the file's (e.g. pmean_s=0.5, ridge=0.01; repeatable)")
    a = ap.parse_args()
    if a.model:
        model = load_model(a.model)
    else:
        from blend.withhlm import train_model

        t0 = time.perf_counter()
        model = train_model(protocols.Gaps().training_set(), fps=120.0)
        model.save(a.save)
        print(f"trained default on TRAIN in {time.perf_counter() - t0:.0f} s; saved {a.save}", file=sys.stderr)
    if a.gate_n0 is not None:
        model.default.settings.gate_n0 = a.gate_n0
        model.default._par[12] = a.gate_n0
    if a.blend_setting:
        model.default = with_settings(model.default, **{k: float(v) for k, v in (x.split("=", 1) for x in a.blend_setting)})
    sets = [setting(s) for s in a.settings]
    if any(sm.get("file") for _, sm in sets) and len(sets) > 1:
        raise SystemExit("'file' must be the only setting (the others change the model's mixing settings)")
    fitted = json.loads(Path(a.band_q).read_text()) if a.band_q else None
    if any(sm["bq"] in ("g", "u") for _, sm in sets) and fitted is None:
        raise SystemExit("settings with BQ g or u need --band-q")
    ones = np.ones_like(np.array(model.band_q, float)) if hasattr(model, "band_q") else None
    own = (np.array(model.band_q, float), model.band_gate) if hasattr(model, "band_q") else None
    if any(sm.get("rate_a", 0.0) > 0 or sm["bq"] == "g" for _, sm in sets) and getattr(model, "rate_ref", None) is None:
        from blend.withhlm import rate_ref

        ts = protocols.Gaps().training_set()
        model.set_rate_ref(rate_ref(ts.sequences, list(model.channels)))
        print("rate_ref from TRAIN (the model file has none)", file=sys.stderr)
    cases = []
    for sd in seeds(a.seeds):
        for c in protocols.Gaps(seed=sd, split=a.split).cases():
            c.info.pop("fk", None)   # joint positions are not this bench's question
            cases.append(c)
    acts = sorted({splits.ACTIVITY[c.test] for c in cases})
    tables: dict[str, dict[str, list]] = {name: {act: [] for act in acts} for name, _ in sets}
    bends: dict[str, dict[str, list]] = {name: {act: [] for act in acts} for name, _ in sets}
    t0 = time.perf_counter()
    for i, c in enumerate(cases):
        given = np.where(c.observed, c.truth, np.nan)
        for name, sm in sets:
            if not sm.get("file"):   # ("file": the model's own mixing settings, untouched)
                model.set_smooth(**{k: v for k, v in sm.items() if k != "bq"})
                if sm["bq"] == "m":
                    if own is not None:
                        model.set_band_q(*own)
                elif sm["bq"] != "0":
                    model.set_band_q(np.array(fitted["M"]), fitted["gate"] if sm["bq"] == "g" else None)   # type: ignore[index]
                elif ones is not None:
                    model.set_band_q(ones)
            fill, std = model.fill_offline(given, c.observed)
            tables[name][splits.ACTIVITY[c.test]].append(metrics.values(c, fill, std, c.info["groups"]))
            bends[name][splits.ACTIVITY[c.test]].append(band_kinks(std, c.observed))
        print(f"  [{i + 1}/{len(cases)}] {c.test} seed {c.info['seed']} ({time.perf_counter() - t0:.0f} s)",
              file=sys.stderr, flush=True)
    out: dict = {"split": a.split, "takes": sorted({c.test for c in cases}), "seeds": seeds(a.seeds),
                 "settings": dict(sets), "activities": {}, "takes_rms": {}}
    for t in out["takes"]:
        row = {}
        for name, _ in sets:
            vs = metrics.Values.concat([v for c, v in zip([c for c in cases if splits.ACTIVITY[c.test] == splits.ACTIVITY[t]],
                                                            tables[name][splits.ACTIVITY[t]]) if c.test == t])
            ok = np.isfinite(vs.hold_err)   # both over the values hold has (a gap at frame 0 has no last value)
            row[name] = float(np.sqrt(np.mean(vs.err[ok] ** 2)))
            row["hold"] = float(np.sqrt(np.mean(vs.hold_err[ok] ** 2)))
        out["takes_rms"][t] = row
    for act in acts + ["all"]:
        row: dict = {}
        for name, _ in sets:
            vs = [v for t in (tables[name].values() if act == "all" else [tables[name][act]]) for v in t]
            pooled = metrics.Values.concat(vs)
            row[name] = {m: x for m, x, _ in metrics.summarise(pooled, by_group_bins=False)}
            r = np.concatenate([v for t in (bends[name].values() if act == "all" else [bends[name][act]]) for v in t])
            row[name]["band_kink_over_10pct"] = float((r > 0.1).mean()) if r.size else 0.0
            row[name]["band_kink_over_25pct"] = float((r > 0.25).mean()) if r.size else 0.0
            if "hold" not in row:
                row["hold"] = {m: x for m, x, _ in metrics.summarise(hold_values(pooled), by_group_bins=False)}
        out["activities"][act] = row
    names = ["hold"] + [n for n, _ in sets]
    print(f"{a.split} ({', '.join(out['takes'])}), seeds {out['seeds']}")
    for act, row in out["activities"].items():
        print(f"\n{act}: " + " | ".join(names))
        for f in FIGS:
            vals = [row[n].get(f) for n in names]
            print(f"  {f:28s} " + "  ".join("-" if v is None else f"{v:8.4f}" for v in vals))
    print("\nper take rms_deg: " + " | ".join(names))
    for t, row in out["takes_rms"].items():
        print(f"  {t:22s} " + "  ".join(f"{row[n]:8.4f}" for n in names))
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
