"""numba's on-disk cache checks a kernel only against its own file's timestamp: a compiled caller
in one file kept the old body of a compiled callee in another after the callee was edited (found
timing hlm/condfill.py, called from hlm/fast.py's kernels).  lacuna.jit.refresh_stale_caches drops
the caches when any such source changes.  Real numba, real cache files, real processes."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from lacuna import jit

ROOT = Path(__file__).resolve().parents[1]

CALLER = textwrap.dedent("""
    from lacuna.jit import jit
    from kpkg.callee import g

    def _f(x):
        return g(x) + 1.0

    f = jit(_f)
""")
RUN = textwrap.dedent("""
    import sys
    from pathlib import Path
    from lacuna.jit import refresh_stale_caches
    pkg = Path(sys.argv[1]) / "kpkg"
    if sys.argv[2] == "refresh":
        refresh_stale_caches([pkg], pkg / "__pycache__" / "stamp")
    from kpkg.caller import f
    print(f(1.0))
""")


def _callee(k: float) -> str:
    return f"from lacuna.jit import jit\n\ndef _g(x):\n    return x * {k}\n\ng = jit(_g)\n"


def _run(tmp: Path, mode: str) -> float:
    env = dict(os.environ, PYTHONPATH=f"{tmp}{os.pathsep}{ROOT}", PYTHONDONTWRITEBYTECODE="1")
    out = subprocess.run([sys.executable, "-c", RUN, str(tmp), mode], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return float(out.stdout.split()[-1])


@pytest.mark.skipif(jit.numba is None, reason="numba is not installed: nothing is compiled or cached")
def test_an_edited_callee_in_another_file_is_recompiled(tmp_path):
    pkg = tmp_path / "kpkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "caller.py").write_text(CALLER)
    (pkg / "callee.py").write_text(_callee(2.0))
    assert _run(tmp_path, "plain") == 3.0
    assert list((pkg / "__pycache__").glob("caller*.nbi")), "numba wrote no cache: the test would prove nothing"
    old = os.stat(pkg / "caller.py").st_mtime_ns
    (pkg / "callee.py").write_text(_callee(5.0))
    os.utime(pkg / "caller.py", ns=(old, old))
    assert _run(tmp_path, "plain") == 3.0   # the trap: numba serves the caller's stale kernel
    assert _run(tmp_path, "refresh") == 6.0  # the caches were dropped: recompiled with the new callee
    assert _run(tmp_path, "refresh") == 6.0  # and the stamp now matches (the caches are kept)
    assert list((pkg / "__pycache__").glob("caller*.nbi"))


def test_unchanged_sources_keep_their_caches(tmp_path):
    pkg = tmp_path / "p"
    (pkg / "__pycache__").mkdir(parents=True)
    (pkg / "m.py").write_text("from lacuna.jit import jit\n")
    (pkg / "__pycache__" / "m._f-1.py311.nbi").write_bytes(b"x")
    stamp = tmp_path / "stamp"
    assert jit.refresh_stale_caches([pkg], stamp)          # no stamp yet: dropped, stamp written
    assert not (pkg / "__pycache__" / "m._f-1.py311.nbi").exists()
    (pkg / "__pycache__" / "m._f-1.py311.nbi").write_bytes(b"x")
    assert not jit.refresh_stale_caches([pkg], stamp)      # same sources: kept
    assert (pkg / "__pycache__" / "m._f-1.py311.nbi").exists()
    (pkg / "m.py").write_text("from lacuna.jit import jit\n# edited\n")
    assert jit.refresh_stale_caches([pkg], stamp)
    assert not (pkg / "__pycache__" / "m._f-1.py311.nbi").exists()
