"""Optional compilation with numba, shared by the compiled single-stream steps
(``hlm.fast``, ``mocap.fastrepr``).

``enabled()`` says whether compiled code may run in this process: numba importable, not turned
off with ``LACUNA_NO_JIT=1``, and the process allowed to execute memory it wrote (systemd's
``MemoryDenyWriteExecute=yes`` forbids that; LLVM would abort the process on the first compiled
call, so it is probed first).  Without it every caller takes its numpy path, which is the
reference the compiled code is tested against.
"""
from __future__ import annotations

import hashlib
import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

try:  # without numba the numpy path serves every stream
    import numba
except (ImportError, OSError):  # not installed, or (PermissionError) this process may not run JIT code
    numba = None  # type: ignore[assignment]


def enabled() -> bool:
    """numba is installed, not turned off (LACUNA_NO_JIT=1), and the process may run code it wrote."""
    return numba is not None and os.environ.get("LACUNA_NO_JIT", "") not in ("1", "true", "yes") and _wx_allowed()


_WX: list[bool] = []


def _wx_allowed() -> bool:
    """May this process make memory it wrote executable?  A JIT must; systemd's
    MemoryDenyWriteExecute=yes forbids it (mprotect fails with EPERM), and LLVM would then abort
    the whole process on the first compiled call.  Probed once with a scratch page."""
    if not _WX:
        _WX.append(_probe_wx())
    return _WX[0]


def _probe_wx() -> bool:
    try:
        import ctypes
        import mmap

        libc = ctypes.CDLL(None, use_errno=True)
        libc.mmap.restype = ctypes.c_void_p
        libc.mmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_long]
        libc.mprotect.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
        libc.munmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t]
        n = mmap.PAGESIZE
        page = libc.mmap(None, n, mmap.PROT_READ | mmap.PROT_WRITE, mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS, -1, 0)
        if page is None or page == ctypes.c_void_p(-1).value:
            return False
        try:
            return libc.mprotect(page, n, mmap.PROT_READ | mmap.PROT_EXEC) == 0
        finally:
            libc.munmap(page, n)
    except (OSError, AttributeError):  # not a POSIX libc (Windows): nothing forbids the JIT there
        return True


_ROOT = Path(__file__).resolve().parents[1]
JIT_PACKAGES = ("lacuna", "mocap", "hlm", "blend", "daemon")  # the packages whose modules compile with ``jit``


def refresh_stale_caches(package_dirs: Iterable[Path], stamp: Path) -> bool:
    """Delete numba's on-disk caches (``__pycache__/*.nbi``, ``*.nbc``) of ``package_dirs`` when the
    source of any module there that compiles with this module's ``jit`` has changed since
    ``stamp`` was written; True if it did.  numba checks a cached kernel only against the
    timestamp of the file that defines it, so a kernel that calls a compiled function of another
    file (hlm.fast's step calls hlm.condfill's ``correct1``) kept running the old callee after an
    edit or an upgrade, until the cache was removed by hand.  Best effort: a read-only install
    keeps what it has (it never wrote a cache either)."""
    dirs = sorted(Path(d) for d in package_dirs)
    h = hashlib.sha1()
    for d in dirs:
        for f in sorted(d.glob("*.py")):
            src = f.read_bytes()
            if b"jit" in src:
                h.update(f.name.encode() + b"\0" + src + b"\0")
    digest = h.hexdigest()
    try:
        if stamp.read_text() == digest:
            return False
    except OSError:
        pass
    try:
        for d in dirs:
            for f in list((d / "__pycache__").glob("*.nb[ic]")):
                f.unlink(missing_ok=True)
        stamp.parent.mkdir(parents=True, exist_ok=True)
        tmp = stamp.with_name(f"{stamp.name}.{os.getpid()}")
        tmp.write_text(digest)
        os.replace(tmp, stamp)
    except OSError:
        return False
    return True


if numba is not None:
    refresh_stale_caches([_ROOT / p for p in JIT_PACKAGES], _ROOT / "lacuna" / "__pycache__" / "jit-sources.sha1")


def jit(fn: Callable[..., Any], **options: Any) -> Callable[..., Any]:
    """numba.njit with an on-disk cache where the package directory is writable (else per process);
    the plain Python function without numba (never called then: callers check ``enabled()``).
    ``options`` go to numba.njit as they are (e.g. ``fastmath``)."""
    if numba is None:
        return fn
    try:
        return numba.njit(cache=True, nogil=True, **options)(fn)
    except RuntimeError:  # no writable cache location (a read-only install): compile per process
        return numba.njit(nogil=True, **options)(fn)


def jit_sums(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``jit`` for a function whose floating-point sums may be reassociated (LLVM's ``reassoc``
    and ``contract``: summed in SIMD lanes, fused multiply-adds), so a dot product runs several
    times faster; its result then differs from the sequential sum in the last bits.  None of
    fastmath's other flags (no NaN/inf assumptions, no approximate functions).  For small pure
    reductions only, whose callers are tested against their numpy reference."""
    return jit(fn, fastmath={"reassoc", "contract"})


