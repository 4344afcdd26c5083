"""Download CMU's public ASF/AMC files into a data directory (``lacuna data fetch cmu``).

Files land in ``<dest>/cmu/<SS>/<SS>.asf`` and ``<dest>/cmu/<SS>/<SS>_<TT>.amc`` (the layout
``mocap.datasets`` reads), ``dest`` defaulting to the per-user cache.  Each file is streamed to
a temporary file beside its destination, checked (byte count against Content-Length, then
parsed as ASF or as AMC against the subject's ASF), and only then renamed into place: an
interrupted or failed download never leaves a partial file under the real name, and a second
run skips every file already there (that is how an interrupted fetch resumes).

Data terms: CMU Graphics Lab Motion Capture Database, mocap.cs.cmu.edu.  Free for research
and commercial use, not for resale.  Credit: "The data used in this project was obtained from
mocap.cs.cmu.edu.  The database was created with funding from NSF EIA-0196217."
"""
from __future__ import annotations

import http.client
import os
import re
import socket
import sys
import time
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

from lacuna import __version__
from lacuna.errors import DataError, ParseError
from mocap.asf import Skeleton, parse_amc, parse_asf, read_asf
from mocap.atomic import atomic_write_bytes
from mocap.datasets import SUBJECT35_RUNS, SUBJECT35_WALKS, cache_dir

CMU_BASE_URL = "http://mocap.cs.cmu.edu/subjects"
# Seconds to wait for the connection and for each read from it.
TIMEOUT_S = 30.0
CHUNK_BYTES = 64 * 1024
# A temporary file older than this (seconds) was left by a killed fetch and may be removed.
STALE_PART_S = 600.0
# Seconds between progress updates on a terminal.
PROGRESS_EVERY_S = 0.2
USER_AGENT = f"lacuna/{__version__} (+data fetch)"
CMU_CREDIT = (
    "The data used in this project was obtained from mocap.cs.cmu.edu. "
    "The database was created with funding from NSF EIA-0196217."
)

# The trials the development data set (../shared/data) holds, fetched when no --trials is given.
CMU_TRIALS: dict[str, list[str]] = {
    "02": ["02_01"],
    "07": ["07_01", "07_02", "07_09", "07_10"],
    "13": ["13_39"],
    "35": sorted(SUBJECT35_WALKS + SUBJECT35_RUNS),
    "49": ["49_18", "49_19", "49_20"],
}


class _Unreachable(DataError):
    """The server cannot be reached at all: trying the remaining files would only wait again."""


@dataclass
class Item:
    """One file to fetch."""

    subject: str
    filename: str
    url: str
    path: Path

    @property
    def is_asf(self) -> bool:
        return self.filename.endswith(".asf")


@dataclass
class FetchReport:
    fetched: list[Path] = field(default_factory=list)
    skipped: list[Path] = field(default_factory=list)
    failed: list[tuple[str, str]] = field(default_factory=list)  # (url, reason)
    n_bytes: int = 0


def subject_id(s: str) -> str:
    """``"7"`` / ``"07"`` -> ``"07"``; ValueError for anything but a subject number."""
    if not re.fullmatch(r"\d{1,3}", s.strip()):
        raise ValueError(f"subject {s!r} is not a CMU subject number (like 07 or 35)")
    return f"{int(s):02d}"


def trial_id(t: str) -> str:
    """``"7_1"`` / ``"07_01"`` -> ``"07_01"``; ValueError otherwise."""
    m = re.fullmatch(r"(\d{1,3})_(\d{1,3})", t.strip())
    if not m:
        raise ValueError(f"trial {t!r} is not a CMU trial name (like 07_01)")
    return f"{int(m.group(1)):02d}_{int(m.group(2)):02d}"


def plan(subjects: list[str], trials: list[str] | None, base_url: str, dest: Path) -> list[Item]:
    """The files to fetch, each subject's ASF before its AMCs."""
    subs = [subject_id(s) for s in subjects]
    tr = [trial_id(t) for t in trials] if trials else None
    if tr:
        for t in tr:
            if t.split("_")[0] not in subs:
                subs.append(t.split("_")[0])
    if not subs:
        raise ValueError("name at least one subject (--subjects 07 35) or trial (--trials 07_01)")
    base = base_url.rstrip("/")
    items: list[Item] = []
    for s in dict.fromkeys(subs):
        if tr:
            names = [t for t in tr if t.split("_")[0] == s]
        elif s in CMU_TRIALS:
            names = CMU_TRIALS[s]
        else:
            raise ValueError(
                f"no default trial list for subject {s} (known: {', '.join(CMU_TRIALS)}); "
                f"name the trials with --trials {s}_01 ..."
            )
        d = dest / "cmu" / s
        for fn in [f"{s}.asf"] + [f"{t}.amc" for t in dict.fromkeys(names)]:
            items.append(Item(s, fn, f"{base}/{s}/{fn}", d / fn))
    return items


class _Progress:
    """Progress on stderr: a live line on a terminal, one line per file otherwise."""

    def __init__(self, out: TextIO, n_files: int):
        self.out, self.n = out, n_files
        self.tty = hasattr(out, "isatty") and out.isatty()
        self.last = 0.0
        self.total = 0

    def update(self, k: int, item: Item, got: int, size: int | None) -> None:
        now = time.monotonic()
        if self.tty and now - self.last >= PROGRESS_EVERY_S:
            self.last = now
            of = f"/{size / 1e3:.1f}" if size else ""
            self.out.write(f"\r[{k}/{self.n}] {item.filename} {got / 1e3:.1f}{of} kB  (total {(self.total + got) / 1e3:.1f} kB)\x1b[K")
            self.out.flush()

    def done(self, k: int, item: Item, status: str, n_bytes: int = 0) -> None:
        self.total += n_bytes
        size = f" {n_bytes / 1e3:.1f} kB" if n_bytes else ""
        cr = "\r" if self.tty else ""
        self.out.write(f"{cr}[{k}/{self.n}] cmu/{item.subject}/{item.filename}{size} {status}  (total {self.total / 1e3:.1f} kB)")
        self.out.write("\x1b[K\n" if self.tty else "\n")
        self.out.flush()


def _download(item: Item, timeout: float, on_bytes) -> bytes:
    """GET one URL; the body, or DataError naming the URL and what went wrong."""
    req = urllib.request.Request(item.url, headers={"User-Agent": USER_AGENT})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as resp:
            length = resp.headers.get("Content-Length")
            size = int(length) if length and length.isdigit() else None
            chunks, got = [], 0
            while True:
                b = resp.read(CHUNK_BYTES)
                if not b:
                    break
                chunks.append(b)
                got += len(b)
                on_bytes(got, size)
    except urllib.error.HTTPError as e:
        raise DataError(f"{item.url}: HTTP {e.code} {e.reason}") from None
    except urllib.error.URLError as e:
        r = e.reason
        if isinstance(r, (TimeoutError, socket.timeout)):
            raise _Unreachable(f"{item.url}: timed out after {timeout:g} s (server not answering)") from None
        raise _Unreachable(f"{item.url}: cannot connect ({getattr(r, 'strerror', None) or r})") from None
    except TimeoutError:
        raise _Unreachable(f"{item.url}: timed out after {timeout:g} s while reading") from None
    except http.client.IncompleteRead as e:
        raise DataError(f"{item.url}: connection closed after {len(e.partial)} bytes (truncated download)") from None
    except (http.client.HTTPException, ConnectionError) as e:
        raise DataError(f"{item.url}: connection failed ({type(e).__name__}: {e})") from None
    if size is not None and got != size:
        raise DataError(f"{item.url}: connection closed after {got} of {size} bytes (truncated download)")
    if got == 0:
        raise DataError(f"{item.url}: empty response")
    return b"".join(chunks)


def _verify(item: Item, body: bytes, skeleton: Skeleton | None) -> Skeleton | None:
    """Parse the downloaded bytes; DataError naming the URL and line when they do not parse."""
    text = body.decode("utf-8", errors="replace")
    try:
        if item.is_asf:
            return parse_asf(text, item.url)
        assert skeleton is not None
        parse_amc(text, skeleton, item.url)
        return None
    except ParseError as e:
        raise DataError(f"downloaded file does not parse, not kept: {e}") from None


def _remove_stale_parts(item: Item) -> None:
    """Delete temporary files a killed fetch left for this file (recent ones may be another fetch's)."""
    now = time.time()
    for p in item.path.parent.glob(f".{item.filename}.*.part"):
        try:
            if now - p.stat().st_mtime > STALE_PART_S:
                p.unlink()
        except FileNotFoundError:
            pass


def _keep(item: Item, body: bytes) -> None:
    """Write atomically: temp file in the same directory, fsync, rename."""
    item.path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(item.path, body)


def fetch_cmu(
    subjects: list[str],
    trials: list[str] | None = None,
    base_url: str = CMU_BASE_URL,
    dest: str | os.PathLike | None = None,
    timeout: float = TIMEOUT_S,
    progress: TextIO | None = None,
) -> FetchReport:
    """Fetch CMU ASF/AMC files into ``dest`` (default: the per-user cache).

    Files already present are skipped.  A failed file is reported and the rest still fetched
    (a subject's AMCs are skipped when its ASF cannot be had: they cannot be checked); at the
    end DataError lists every failure.  Nothing partial is ever left under a real file name.
    """
    dest = Path(dest) if dest is not None else cache_dir()
    items = plan(subjects, trials, base_url, dest)
    out = progress if progress is not None else sys.stderr
    prog = _Progress(out, len(items))
    rep = FetchReport()
    skeletons: dict[str, Skeleton | None] = {}
    for k, item in enumerate(items, 1):
        try:
            if not item.is_asf and skeletons.get(item.subject) is None:
                raise DataError(f"{item.url}: not fetched, the subject's ASF is unavailable")
            if item.path.exists():
                if item.is_asf:
                    try:
                        skeletons[item.subject] = read_asf(item.path)
                    except ParseError as e:
                        raise DataError(f"{item.path} is already there but does not parse ({e}); delete it and fetch again") from None
                rep.skipped.append(item.path)
                prog.done(k, item, "already here")
                continue
            if item.path.parent.is_dir():
                _remove_stale_parts(item)
            body = _download(item, timeout, lambda got, size, k=k, item=item: prog.update(k, item, got, size))
            skel = _verify(item, body, skeletons.get(item.subject))
            if item.is_asf:
                skeletons[item.subject] = skel
            _keep(item, body)
            rep.fetched.append(item.path)
            rep.n_bytes += len(body)
            prog.done(k, item, "ok", len(body))
        except DataError as e:
            if item.is_asf:
                skeletons[item.subject] = None
            rep.failed.append((item.url, str(e)))
            prog.done(k, item, "FAILED")
            out.write(f"  {e}\n")
            if isinstance(e, _Unreachable):
                rest = items[k:]
                rep.failed += [(it.url, f"{it.url}: not tried (server unreachable)") for it in rest]
                out.write(f"  giving up on the {len(rest)} remaining files\n")
                break
    out.write(
        f"fetched {len(rep.fetched)} files ({rep.n_bytes / 1e3:.1f} kB), {len(rep.skipped)} already here, "
        f"{len(rep.failed)} failed, into {dest}\n"
    )
    if rep.fetched:
        out.write(f"CMU data terms: free to use, not to resell; credit: {CMU_CREDIT}\n")
    if rep.failed:
        shown = [r for _, r in rep.failed if "not tried" not in r]
        more = len(rep.failed) - len(shown)
        lines = "\n  ".join(shown + ([f"... and {more} files not tried"] if more else []))
        raise DataError(f"{len(rep.failed)} of {len(items)} files not fetched (run again to retry; fetched files are kept):\n  {lines}")
    return rep
