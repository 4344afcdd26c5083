"""A harness process that dies without stopping its daemon leaves the daemon behind, stopped for
good if it was held stopped (the starved soak SIGSTOPs its daemon).  ``sweep_orphans()`` finds
such daemons by the owner tag the harness puts in their environment and kills them; a daemon whose
harness is alive is never touched.  Real processes throughout."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

from waiting import wait_until

from clients.harness import OWNER_ENV, DaemonProcess, orphans, sweep_orphans

ROOT = Path(__file__).resolve().parents[1]

OWNER = textwrap.dedent("""
    import json, signal, sys, time
    from clients.harness import DaemonProcess
    d = DaemonProcess({"pt": {"builtin": "passthrough", "channels": ["a", "b"]}}, workdir=sys.argv[1]).start()
    d.signal(signal.SIGSTOP)
    print(json.dumps({"daemon": d.pid}), flush=True)
    time.sleep(600)
""")


def _state(pid: int) -> str | None:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return None


def test_a_stopped_daemon_whose_harness_was_killed_is_swept(tmp_path):
    owner = subprocess.Popen([sys.executable, "-c", OWNER, str(tmp_path)], cwd=ROOT, stdout=subprocess.PIPE,
                             env=dict(os.environ, PYTHONPATH=str(ROOT)))
    daemon = None
    try:
        line = owner.stdout.readline()  # type: ignore[union-attr]
        assert line, f"the owner process exited with {owner.wait()} before starting its daemon"
        daemon = json.loads(line)["daemon"]
        wait_until(lambda: _state(daemon) == "T", 30, "the daemon held stopped")
        assert daemon not in orphans()  # its harness is alive
        owner.kill()   # as a CI timeout or a second Ctrl-C would: no stop(), no atexit
        owner.wait(30)
        assert _state(daemon) == "T"  # left behind, stopped: what the sweep is for
        assert daemon in orphans()
        assert daemon in sweep_orphans()  # (other orphans on the machine may be swept with it)
    finally:
        if owner.poll() is None:
            owner.kill()
            owner.wait(30)
    wait_until(lambda: _state(daemon) in (None, "Z"), 30, "the swept daemon ended")
    assert daemon not in orphans()


def test_a_daemon_whose_harness_is_alive_is_not_touched(tmp_path):
    d = DaemonProcess({"pt": {"builtin": "passthrough", "channels": ["a", "b"]}}, workdir=tmp_path)
    assert d.env[OWNER_ENV].startswith(f"{os.getpid()}:")
    with d:
        assert d.pid not in orphans()
        assert d.pid not in sweep_orphans()
        assert d.alive()
    assert d.returncode == 0
