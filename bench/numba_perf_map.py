"""Name numba's compiled functions for ``perf``: write ``/tmp/perf-PID.map`` (perf's map of JIT
code, read by ``perf report`` / ``perf script``) for every function compiled in this process, and
optionally dump their machine code for objdump (bench/notebook/hlm64-6.md's profile).

numba's on-disk cache keeps object code only, so a library loaded from it has no module to list:
profile a process that compiled its kernels itself (``NUMBA_CACHE_DIR`` set to a fresh directory).
In the process to profile, after its kernels have run once::

    from bench.numba_perf_map import write_map
    write_map()          # then, from a shell: perf record -F 4000 -p PID -- sleep 10

``dump_code(["_step_in"], outdir)`` writes each matching function's bytes to
``outdir/NAME-ADDRESS.bin``; ``objdump -D -b binary -m i386:x86-64 --adjust-vma=0xADDRESS FILE``
disassembles one at its address, so perf's sample addresses (``perf script -F ip``) fall on its
instructions.
"""
from __future__ import annotations

import ctypes
import gc
import os
from pathlib import Path


def _functions() -> dict[int, str]:
    from numba.core.codegen import JITCodeLibrary

    found: dict[int, str] = {}
    for lib in [o for o in gc.get_objects() if isinstance(o, JITCodeLibrary)]:
        try:
            fns = list(lib._final_module.functions)
        except Exception:  # noqa: BLE001 - a library loaded from the cache, or not finalized
            continue
        for fn in fns:
            if fn.is_declaration:
                continue
            try:
                addr = lib.get_pointer_to_function(fn.name)
            except Exception:  # noqa: BLE001
                continue
            if addr:
                found[addr] = fn.name
    return found


def write_map(path: str | None = None) -> int:
    """Write perf's map for this process; returns how many functions it names.  A function's size
    is taken to its next neighbour's start (4 kB for the last)."""
    found = _functions()
    starts = sorted(found)
    out = Path(path or f"/tmp/perf-{os.getpid()}.map")
    with out.open("w") as fh:
        for i, a in enumerate(starts):
            nxt = starts[i + 1] - a if i + 1 < len(starts) else 0
            size = nxt if 0 < nxt < 1 << 20 else 4096
            fh.write(f"{a:x} {size:x} {found[a]}\n")
    return len(starts)


def dump_code(patterns: list[str], outdir: str, path: str | None = None) -> int:
    """Dump the machine code of the map's functions whose names contain one of ``patterns``."""
    os.makedirs(outdir, exist_ok=True)
    n = 0
    for line in Path(path or f"/tmp/perf-{os.getpid()}.map").read_text().splitlines():
        a, size, name = line.split()
        hit = [p for p in patterns if p in name]
        if hit:
            start, nbytes = int(a, 16), int(size, 16)
            Path(outdir, f"{hit[0]}-{start:x}.bin").write_bytes(ctypes.string_at(start, nbytes))
            n += 1
    return n
