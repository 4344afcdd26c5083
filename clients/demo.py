"""``lacuna demo``: the whole product on one machine in a couple of minutes.

1. motion: the CMU takes in the data directory; else ``lacuna data fetch`` (when this build has
   it and the network answers); else the built-in synthetic gait generator (it says so).  From
   the data it trains on the TRAIN split's takes whose CMU subject is named (subjects 07 and 35:
   walks and runs; 13 and 49: non-locomotion; mocap/splits.py) and replays a TEST take of a
   performer none of them is from (02_01, subject 02, by default; ``--take`` picks another test
   take);
2. trains ``default`` and a small HLM (``--methods`` picks others; small settings for hlm and
   crbm, chosen for speed, not on validation) plus hold-last-value, and the offline linear
   interpolation as a reference;
3. starts ``lacuna serve`` as a real subprocess on a loopback port serving them;
4. replays the held-out take in real time through the daemon once per causal method, with every
   joint group dropping out in bursts of 0.1-2 s (the gaps protocol's generator, through
   ``clients.takes.drop_mask``); ``interp`` is computed in-process (it needs the future: no live
   system can run it);
5. scores every fill with ``mocap.metrics`` (the scoring of ``lacuna eval``): RMS by gap length,
   onset figures, calibration; prints them beside the round-trip percentiles and writes a plot
   of the fill with its 2-std band against the truth, hold and interp, a latency histogram and a
   JSON report with every figure.

The daemon is stopped in a ``finally`` (and at exit), so Ctrl-C never leaves it running.
"""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from clients import demo_score, synth
from clients import replay as rp
from clients.harness import DaemonProcess
from clients.takes import drop_mask
from lacuna import registry
from lacuna.errors import LacunaError
from mocap.motion import Motion
from mocap.protocols import GAP_GROUPS, TrainingSet

TEST_TAKE = "02_01"
DROP = "gaps"  # the gaps protocol's bursts on every joint group (the root keeps its markers)
# default, and the papers' HLM with small settings (it fits the two-minute budget: 79 s of
# training measured on this 2-core machine under load; the small CRBM did not finish in 8 minutes)
MODELS = ("default", "hlm")
CAUSAL_BASELINES = ("hold",)  # served by the daemon beside the models
OFFLINE = "interp"  # in-process: needs the future
# Small settings so hlm (and crbm, when asked for) train in about a minute on two cores: chosen
# for speed, not on validation, and reported so; a method ignores the options it does not know
# (lacuna.registry.MethodSpec).
SMALL = {
    "hlm": {"n_iter": 10, "styles": 2, "restarts": 1, "progress": False},
    "default": {"n_iter": 10, "styles": 2, "restarts": 1, "progress": False},   # its HLM expert's
    "crbm": {"hidden": 100, "epochs": 400, "order": 3, "progress": False},
}
TRAIN_OPTIONS = {"fps": 120.0, "cycle_frames": 140}
SEED_TRIES = 20
FETCH_SUBJECTS = ["02", "07", "13", "35", "49"]


def say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def performer(take: str) -> str | None:
    """CMU subject of a ``NN_MM`` take; None where the data does not say (the ``cmu_li`` takes)."""
    head, _, tail = take.partition("_")
    return head if head.isdigit() and tail.isdigit() else None


def train_takes(test: str) -> list[str]:
    """The TRAIN split's takes whose performer is named and is not the replayed take's."""
    from mocap import splits

    return [t for t in splits.TRAIN if performer(t) is not None and performer(t) != performer(test)]


def check_take(take: str) -> None:
    from mocap import splits

    if splits.split_of(take) != "test":
        raise LacunaError(f"--take {take}: the demo replays a TEST take of mocap.splits "
                          f"(one of {', '.join(splits.TEST)}); {take} is {splits.split_of(take) or 'not in the split'}")


def get_motion(source: str, take: str) -> tuple[list[Motion], list[str], Motion, str, str]:
    """(training takes, their names, held-out take, its name, a sentence saying where they came from)."""
    if source in ("auto", "data"):
        got = _from_data(take)
        if got is None and source == "auto":
            got = _fetch_then_data(take)
        if got is not None:
            return got
        if source == "data":
            raise LacunaError("no CMU data directory (set LACUNA_DATA or run "
                              f"`lacuna data fetch cmu --subjects {' '.join(FETCH_SUBJECTS)}`)")
    train = synth.trials(6, seconds=6.0, seed=1)
    test = synth.gait(5.0, seed=100)
    return (train, [m.source for m in train], test, test.source,
            "SYNTHETIC gait (no CMU data directory and no download): the numbers below show the machinery working, "
            "not accuracy on real motion")


def _from_data(take: str) -> tuple[list[Motion], list[str], Motion, str, str] | None:
    from mocap import datasets, splits

    try:
        if datasets.data_dir() is None:
            return None
        names = train_takes(take)
        train = [splits.load_take(t) for t in names]
        test = splits.load_take(take)
    except (LacunaError, OSError):
        return None
    who = (f"subject {performer(take)}" if performer(take) else
           "cmu_li: the data does not name its performer, so it may be one the training takes share")
    return (train, names, test, take,
            f"CMU motion capture from {datasets.data_dir()}: trained on {len(names)} TRAIN takes of subjects "
            f"{', '.join(sorted({str(performer(t)) for t in names}))} ({', '.join(names)}); replaying TEST take {take} ({who})")


def _fetch_then_data(take: str) -> tuple[list[Motion], list[str], Motion, str, str] | None:
    from lacuna.cli import build

    cli = build()
    if "data" not in cli.parser._subparsers._group_actions[0].choices:  # type: ignore[union-attr,operator]
        say("no data directory, and this build has no `lacuna data fetch`")
        return None
    say(f"no data directory: trying `lacuna data fetch cmu --subjects {' '.join(FETCH_SUBJECTS)}` ...")
    r = subprocess.run([sys.executable, "-m", "lacuna.cli", "data", "fetch", "cmu", "--subjects", *FETCH_SUBJECTS],
                       stdin=subprocess.DEVNULL)
    if r.returncode != 0:
        say("download failed (offline?)")
        return None
    return _from_data(take)


def train_models(train: list[Motion], names: list[str], workdir: Path, methods: list[str],
                 options: dict[str, dict[str, Any]]) -> tuple[dict[str, Path], dict[str, float], list[str]]:
    """Train and save each method; returns ({name: file}, {name: seconds}, notes)."""
    from mocap import splits

    ch = train[0].channels
    ts = TrainingSet([m.frames[:, m.index(ch)] for m in train], list(ch), train[0].fps, list(names),
                     [splits.ACTIVITY.get(n, "walk") for n in names])
    known = registry.methods()
    files: dict[str, Path] = {}
    secs: dict[str, float] = {}
    notes = []
    for name in methods:
        if name not in known:
            notes.append(f"{name}: not registered in this build (lacuna methods lists {', '.join(known)}); skipped")
            say(f"  {notes[-1]}")
            continue
        say(f"training {name} on {ts.n_frames} frames ...")
        t0 = time.perf_counter()
        spec = registry.get_method(name)
        model = spec.train(ts, **{**TRAIN_OPTIONS, **spec.defaults, **options.get(name, {})})
        secs[name] = time.perf_counter() - t0
        f = workdir / f"{name}.npz"
        model.save(str(f))
        files[name] = f
        say(f"  {name}: {secs[name]:.1f} s -> {f}")
    return files, secs, notes


def choose_seed(test: Motion, first: int) -> int:
    """Of SEED_TRIES seeds from ``first``, the first whose bursts include at least two short
    (0.1-0.25 s) and two long (0.5-2 s) ones; else the one with the most of the rarer kind."""
    def kinds(s: int) -> tuple[int, int]:
        c = demo_score.gap_lengths(drop_mask(DROP, test, s)[1], test.fps)
        return c["short (0.1-0.25 s)"], c["long (0.5-2 s)"]

    best, best_k = first, -1
    for s in range(first, first + SEED_TRIES):
        k = min(kinds(s))
        if k >= 2:
            return s
        if k > best_k:
            best, best_k = s, k
    return best


def offline_fill(name: str, path: Path, test: Motion, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The model file run in-process on the same take and mask (interp; and the check that the
    daemon's causal fill matches the same model offline)."""
    from lacuna.modelfile import load_model

    model = load_model(str(path))
    given = np.where(obs, test.frames, np.nan)
    filled, std = registry.get_method(name).run(model, given, obs.copy())
    filled = np.asarray(filled, np.float64)
    return filled, np.zeros_like(filled) if std is None else np.asarray(std, np.float64)


def run(args: Any) -> int:
    t_start = time.perf_counter()
    take = getattr(args, "take", None) or TEST_TAKE
    if args.source != "synthetic":
        check_take(take)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    train, names, test, test_name, where = get_motion(args.source, take)
    say(f"motion: {where}")
    wanted = [m for m in (list(MODELS) if not args.methods else args.methods.split(",")) if m and m != "none"]
    # the models' own progress lines (EM iterations, CD epochs) go to stderr unless --quiet
    options = {k: {**v, "progress": not args.quiet} for k, v in SMALL.items()}
    files, secs, notes = train_models(train, names, out, list(dict.fromkeys(wanted + list(CAUSAL_BASELINES) + [OFFLINE])),
                                      options)
    served = [m for m in wanted if m in files and registry.get_method(m).causal]
    offline = list(dict.fromkeys([m for m in wanted if m in files and m not in served] + [OFFLINE]))
    for m in served:
        if m in SMALL:
            notes.append(f"{m}: small demo settings ({', '.join(f'{k}={v}' for k, v in SMALL[m].items() if k != 'progress')}), "
                         "chosen for speed, not on validation")
    if "default" not in served:
        notes.append("`default` is not served in this run: the table shows the baselines only" if not served else
                     "`default` is not served in this run (--methods)")
        say(f"  {notes[-1]}")
    ch = train[0].channels
    test = test.select(ch) if test.channels != ch else test
    seed = choose_seed(test, args.seed)
    obs, bursts = drop_mask(DROP, test, seed)
    lengths = demo_score.gap_lengths(bursts, test.fps)
    drops = (f"{len(bursts)} bursts on {len({g for g, _, _ in bursts})} joint groups "
             f"({', '.join(f'{v} {k}' for k, v in lengths.items() if v)}), {int((~obs).sum())} values missing; "
             f"the gaps protocol's generator, seed {seed}")
    say(f"held-out take {test_name}: {test.n_frames} frames at {test.fps:g} Hz; {drops}")
    live = list(dict.fromkeys(served + [b for b in CAUSAL_BASELINES if b in files]))
    # overdue = "serve": a frame the loaded machine cannot answer within the budget is filled late
    # rather than dropped, so every replayed frame carries the daemon's own fill and std and the
    # accuracy figures do not depend on the load (lateness shows in the round trips)
    daemon = DaemonProcess({k: str(files[k]) for k in live}, live[0], workdir=str(out / "daemon"),
                           daemon={"budget_ms": float(args.budget_ms), "overdue": "serve"})
    notes.append(f"the daemon ran with overdue = \"serve\" (budget {args.budget_ms:g} ms): frames it could not "
                 "answer in time were filled late, not dropped (a live deployment's default drops them)")
    runs: dict[str, rp.ReplayResult] = {}
    try:
        say(f"starting lacuna serve on {daemon.endpoint} (the first start after an install compiles the fill "
            "kernels: about a minute) ...")
        daemon.start()
        for name in live:
            say(f"replaying {test_name} through the daemon with {name} (speed x{args.speed:g}) ...")
            runs[name] = rp.replay(daemon.endpoint, test, obs, speed=args.speed, stream=f"demo-{name}", model=name,
                                   progress=not args.quiet)
    finally:
        daemon.stop()
    case = demo_score.make_case(test_name, test.frames, obs, ch, test.fps,
                                _cm_per_unit(test), f"{DROP} seed {seed}")
    results: dict[str, dict[str, Any]] = {}
    fills: dict[str, np.ndarray] = {}
    stds: dict[str, np.ndarray] = {}
    for name, r in runs.items():
        summ = rp.summary(r)
        fills[name], stds[name] = r.filled, r.std
        off, off_std = offline_fill(name, files[name], test, obs)
        off_scores = demo_score.score(case, off, off_std)
        results[name] = {"through_daemon": True, "causal": True, "scores": demo_score.score(case, r.filled, r.std),
                         "latency": summ["latency"], "status": summ["status"], "dropped_frames": summ["dropped"],
                         "daemon_proc_ms_p50": summ["daemon_proc_ms_p50"], "replay_wall_s": summ["wall_s"],
                         "offline_rms_deg": off_scores["rms_deg"], "offline_nll_per_value": off_scores["nll_per_value"]}
    for name in (m for m in offline if m in files):
        f, s = offline_fill(name, files[name], test, obs)
        fills[name], stds[name] = f, s
        results[name] = {"through_daemon": False, "causal": False, "scores": demo_score.score(case, f, s),
                         "latency": None, "note": f"{name} is offline, computed in-process: it uses frames after each "
                                                  "gap, so no live system can run it"}
        notes.append(f"{name} is offline (it uses frames after each gap): a reference, not a live option")
    report = {"motion": where, "train_takes": names, "train_seconds": secs, "notes": notes,
              "take": {"name": test_name, "frames": int(test.n_frames), "fps": test.fps, "split": _split(test_name, args),
                       "performer": performer(test_name) if args.source != "synthetic" else None,
                       "about": f"{test_name} ({_split(test_name, args)}), {test.n_frames / test.fps:.1f} s at "
                                f"{test.fps:g} Hz, replayed at x{args.speed:g} through lacuna serve"},
              "dropouts": {"pattern": DROP, "seed": seed, "lengths": lengths, "bursts": [list(b) for b in bursts],
                           "missing_values": int((~obs).sum()), "about": drops},
              "results": results, "total_seconds": 0.0}
    report["plots"] = plots(out, test, test_name, obs, fills, stds, served,
                            {k: r.rtt_ms for k, r in runs.items()})
    report["total_seconds"] = time.perf_counter() - t_start
    rp.write_json(str(out / "demo.json"), report)
    print(demo_score.format_report(report))
    return 0


def _split(name: str, args: Any) -> str:
    if args.source == "synthetic" or name.startswith("synthetic"):
        return "synthetic"
    from mocap import splits

    return splits.split_of(name) or "external"


def _cm_per_unit(m: Motion) -> float | None:
    from mocap.metrics import cm_per_unit

    return cm_per_unit(m.skeleton)


def plots(out: Path, test: Motion, name: str, obs: np.ndarray, fills: dict[str, np.ndarray],
          stds: dict[str, np.ndarray], served: list[str], rtts: dict[str, np.ndarray]) -> dict[str, str]:
    erased = ~obs
    band = "default" if "default" in fills else (served[0] if served else next(iter(fills)))
    others = {k: v for k, v in fills.items() if k != band}
    cols = rp.band_channels(test.frames, erased, test.channels, GAP_GROUPS)
    fig = rp.plot_fill_band(str(out / "fills.png"), test.frames, fills[band], stds[band], erased, test.channels,
                            test.fps, cols, others, band,
                            f"{name}: dropouts of 0.1-2 s; truth, {band} through the daemon with its 2-std band, "
                            + ", ".join(f"{k}{'' if registry.get_method(k).causal else ' (offline)'}" for k in others))
    hist = rp.plot_latency(str(out / "latency.png"), rtts, "round trip per frame, lacuna serve on loopback")
    return {"fills": fig, "latency": hist}
