"""A batch fill: which takes still need doing, one Dask task per take, progress, the summary.

The model file is read once here and shipped to every worker once
(``client.scatter(..., broadcast=True)``); each task gets a reference to it, never a copy, and
a worker loads it on its first take and keeps it (``archive.fill.model_from_bytes``).  A take
whose output is complete and newer than its input and the model is not submitted again, so a
rerun after an interruption does only what is missing.  Tasks are idempotent and write through
temporary names: a worker killed mid-take leaves at most a temporary file (swept at the end), the
scheduler gives the take to another worker, and no output is ever half written.
"""
from __future__ import annotations

import glob
import os
import sys
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from archive.fill import FillSpec, fill_take, is_done
from archive.formats import sha256_file
from archive.takes import TakeJob

# a task that raised inside the worker (not a bad take: those come back as rows) is tried again
TASK_RETRIES = 2
PROGRESS_WIDTH = 28
# Dask runs higher priorities first; the takes' priorities are their sizes in bytes
WARM_PRIORITY = 1 << 40
WARM_WAIT_S = 30


@dataclass
class BatchResult:
    rows: list[dict[str, Any]]                 # one per take, in the batch's order
    skipped: list[str] = field(default_factory=list)
    wall_s: float = 0.0
    ship_s: float = 0.0                        # model scattered to the workers
    workers: int = 0
    scheduler: str = ""
    warm: list[dict[str, Any]] = field(default_factory=list)   # archive.warmup.warm's timers per worker

    @property
    def failed(self) -> list[dict[str, Any]]:
        return [r for r in self.rows if r["status"] == "failed"]

    def summary(self) -> dict[str, Any]:
        done = [r for r in self.rows if r["status"] == "filled"]
        frames = sum(r["frames"] for r in done)
        work = sum(r["seconds"]["total"] for r in self.rows)
        return {
            "takes": len(self.rows) + len(self.skipped), "filled": len(done), "skipped": len(self.skipped),
            "failed": len(self.failed), "frames": frames, "values_filled": sum(r["values_filled"] for r in done),
            "held_values": sum(r.get("held_values", 0) for r in done),
            "wall_s": round(self.wall_s, 3), "work_s": round(work, 3), "model_ship_s": round(self.ship_s, 4),
            "takes_per_s": round(len(done) / self.wall_s, 3) if self.wall_s > 0 else None,
            "frames_per_s": round(frames / self.wall_s, 1) if self.wall_s > 0 else None,
            "workers": self.workers, "scheduler": self.scheduler,
            "failures": [{"source": r["source"], "error": r["error"]} for r in self.failed],
        }


class Progress:
    """A one-line bar on stderr: takes done / total, failures, rate, time left."""

    def __init__(self, total: int, enabled: bool = True, stream=sys.stderr):
        self.total, self.enabled, self.stream = total, enabled and total > 0, stream
        self.done = self.failed = 0
        self.t0 = time.perf_counter()

    def update(self, ok: bool) -> None:
        self.done += 1
        self.failed += 0 if ok else 1
        if not self.enabled:
            return
        el = time.perf_counter() - self.t0
        rate = self.done / el if el > 0 else 0.0
        left = (self.total - self.done) / rate if rate > 0 else 0.0
        n = int(PROGRESS_WIDTH * self.done / self.total)
        bar = "#" * n + "-" * (PROGRESS_WIDTH - n)
        print(f"\rfill [{bar}] {self.done}/{self.total} takes, {self.failed} failed, {rate:.2f} takes/s, "
              f"{left:.0f} s left ", end="" if self.done < self.total else "\n", file=self.stream, flush=True)


def pending(jobs: list[TakeJob], spec: FillSpec, model_file: str | None) -> tuple[list[TakeJob], list[TakeJob]]:
    """(to do, already done) for a batch."""
    todo, done = [], []
    for j in jobs:
        (done if is_done(j, spec, model_file) else todo).append(j)
    return todo, done


def sweep_temporaries(jobs: list[TakeJob]) -> int:
    """Remove temporary files a killed worker left beside the batch's outputs; how many."""
    n = 0
    for j in jobs:
        d, b = os.path.split(j.output)
        for p in glob.glob(os.path.join(glob.escape(d), f".{glob.escape(b)}.*.part")):
            try:
                os.unlink(p)
                n += 1
            except FileNotFoundError:
                pass
    return n


def run_batch(jobs: list[TakeJob], spec: FillSpec, model_file: str | None, client=None, progress: bool = True,
              on_row: Callable[[dict[str, Any]], None] | None = None, warm: bool = True) -> BatchResult:
    """Fill every take of ``jobs`` not already done; on ``client``'s cluster, else in this process.
    ``warm``: each worker first runs ``archive.warmup.warm`` (imports, model) as a task of its own."""
    t0 = time.perf_counter()
    todo, done = pending(jobs, spec, model_file)
    blob = None
    if model_file:
        with open(model_file, "rb") as fh:
            data = fh.read()
        blob = (spec.model_sha256 or sha256_file(model_file), data)
    bar = Progress(len(todo), progress)
    rows: dict[int, dict[str, Any]] = {}
    res = BatchResult([], [j.source for j in done])

    def take(row: dict[str, Any]) -> None:
        rows[row["index"]] = row
        bar.update(row["status"] == "filled")
        if on_row:
            on_row(row)

    if client is None:
        for j in todo:
            take(fill_take(j, spec, blob))
    elif todo:
        from distributed import as_completed

        from archive.cluster import describe

        info = describe(client)
        res.workers, res.scheduler = info["workers"], info["scheduler"]
        ts = time.perf_counter()
        ref = client.scatter(blob, broadcast=True, hash=False) if blob is not None else None
        res.ship_s = time.perf_counter() - ts
        token = uuid.uuid4().hex[:12]
        warming = []
        if warm:
            from archive.warmup import warm as warm_fn

            # one start-up task per worker (imports, model), ahead of every take; not waited for: a
            # worker lost meanwhile leaves its warm-up to run on another one or not at all
            for i, addr in enumerate(client.scheduler_info()["workers"]):
                warming.append(client.submit(warm_fn, ref, key=f"lacuna-warm-{token}-{i}", workers=[addr],
                                             allow_other_workers=True, pure=False, priority=WARM_PRIORITY))
        by_key = {}
        futures = []
        for j in todo:
            size = os.path.getsize(j.source) if os.path.exists(j.source) else 0
            # the largest takes first, so the batch does not end on one worker's long take
            f = client.submit(fill_take, j, spec, ref, key=f"lacuna-fill-{token}-{j.index}", pure=False,
                              retries=TASK_RETRIES, priority=size)
            by_key[f.key] = j
            futures.append(f)
        for f in as_completed(futures):
            j = by_key[f.key]
            try:
                row = f.result()
            except Exception as e:  # the task itself failed on every try (e.g. workers kept dying)
                row = {"index": j.index, "source": j.source, "output": j.output, "status": "failed",
                       "error": f"task failed on the cluster: {type(e).__name__}: {e}", "seconds": {"total": 0.0}}
            take(row)
        if warming:  # a worker that got no take may still be warming up: its record, briefly waited for
            from distributed import wait

            try:
                wait(warming, timeout=WARM_WAIT_S)
            except TimeoutError:
                pass
        res.warm = [f.result() for f in warming if f.status == "finished"]
        del ref, warming
    res.rows = [rows[j.index] for j in todo]
    sweep_temporaries(jobs)
    res.wall_s = time.perf_counter() - t0
    return res
