"""clients.harness.DaemonProcess with ``argv``: a wrapper around ``daemon.loop.serve`` (what a benchmark
that times the daemon's parts runs) is started, waited for and stopped as ``lacuna serve`` is.  A real
process on loopback."""
from __future__ import annotations

import os
import sys
import textwrap
from pathlib import Path

from clients.client import control
from clients.harness import DaemonProcess

ROOT = Path(__file__).resolve().parents[1]

WRAPPER = textwrap.dedent("""
    import sys
    from pathlib import Path
    Path(sys.argv[1]).write_text(sys.argv[2])   # what it was given: the config's path, appended by the harness
    from daemon.loop import serve
    sys.exit(serve(sys.argv[2]))
""")


def test_a_wrapper_given_as_argv_is_served_as_lacuna_serve(tmp_path):
    wrapper, seen = tmp_path / "wrapper.py", tmp_path / "seen.txt"
    wrapper.write_text(WRAPPER)
    d = DaemonProcess({"pt": {"builtin": "passthrough", "channels": ["a", "b"]}}, workdir=str(tmp_path / "d"),
                      env={"PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")},
                      argv=[sys.executable, str(wrapper), str(seen)])
    with d.start():
        assert seen.read_text() == str(d.config_path)
        assert control(d.endpoint, "status", timeout_s=5.0).result["models"]["pt"]
    assert d.returncode == 0
