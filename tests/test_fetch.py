"""``lacuna data fetch cmu`` against a real HTTP server on loopback laid out like CMU's site.

The site is a temporary directory holding copies of a few files from the real data directory
(``subjects/07/07.asf``, ``subjects/07/07_01.amc``, ...); the command runs as a real subprocess.
"""
from __future__ import annotations

import filecmp
import http.server
import os
import shutil
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from lacuna.cli import main
from mocap.fetch import CMU_TRIALS, plan

RUN_TIMEOUT_S = 60  # a hung fetch fails the test instead of hanging the suite


class _Handler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):  # keep the test output clean; requests are recorded instead
        pass

    def do_GET(self):
        srv = self.server
        srv.requests.append(self.path)
        if self.path in srv.hang:
            srv.release.wait(RUN_TIMEOUT_S)
            return
        if self.path in srv.truncate:
            body = (Path(srv.root) / self.path.lstrip("/")).read_bytes()
            self.send_response(200)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body[: len(body) // 2])
            self.wfile.flush()
            self.close_connection = True
            return
        super().do_GET()


@pytest.fixture
def site(data, tmp_path):
    """A CMU-like site on 127.0.0.1 (random port) serving subject 07's ASF and three trials."""
    root = tmp_path / "site"
    d = root / "subjects" / "07"
    d.mkdir(parents=True)
    for fn in ("07.asf", "07_01.amc", "07_02.amc", "07_09.amc"):
        shutil.copy(data / "cmu" / "07" / fn, d / fn)
    handler = lambda *a, **kw: _Handler(*a, directory=str(root), **kw)
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    srv.root, srv.requests, srv.hang, srv.truncate = str(root), [], set(), set()
    srv.release = threading.Event()
    t = threading.Thread(target=srv.serve_forever, daemon=True)
    t.start()
    srv.base_url = f"http://127.0.0.1:{srv.server_address[1]}/subjects"
    try:
        yield srv
    finally:
        srv.release.set()
        srv.shutdown()
        srv.server_close()
        t.join(5)


def _fetch(site_url: str, dest: Path, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, XDG_CACHE_HOME=str(dest.parent / "xdg-cache"))
    cmd = [sys.executable, "-m", "lacuna.cli", "data", "fetch", "cmu", "--base-url", site_url, "--dest", str(dest), *args]
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=RUN_TIMEOUT_S, check=False)


def _leftovers(dest: Path) -> list[str]:
    return sorted(p.name for p in dest.rglob("*") if p.name.endswith(".part"))


def test_fetch_downloads_identical_files_then_skips_them(site, data, tmp_path):
    dest = tmp_path / "dest"
    r = _fetch(site.base_url, dest, "--subjects", "07", "--trials", "07_01", "07_02")
    assert r.returncode == 0, r.stderr
    for fn in ("07.asf", "07_01.amc", "07_02.amc"):
        assert filecmp.cmp(dest / "cmu" / "07" / fn, data / "cmu" / "07" / fn, shallow=False), fn
    assert sorted(p.name for p in (dest / "cmu" / "07").iterdir()) == ["07.asf", "07_01.amc", "07_02.amc"]
    assert site.requests == ["/subjects/07/07.asf", "/subjects/07/07_01.amc", "/subjects/07/07_02.amc"]
    # progress on stderr: files and bytes
    size = (data / "cmu" / "07" / "07_02.amc").stat().st_size
    assert f"[3/3] cmu/07/07_02.amc {size / 1e3:.1f} kB ok" in r.stderr
    assert "fetched 3 files" in r.stderr and "0 failed" in r.stderr

    site.requests.clear()
    r2 = _fetch(site.base_url, dest, "--subjects", "07", "--trials", "07_01", "07_02")
    assert r2.returncode == 0, r2.stderr
    assert site.requests == []
    assert r2.stderr.count("already here") == 3 + 1  # three lines, plus the summary's count
    assert "fetched 0 files (0.0 kB), 3 already here" in r2.stderr


def test_fetch_resumes_after_an_interrupted_run(site, tmp_path):
    dest = tmp_path / "dest"
    assert _fetch(site.base_url, dest, "--trials", "07_01").returncode == 0
    site.requests.clear()
    r = _fetch(site.base_url, dest, "--trials", "07_01", "07_02", "07_09")
    assert r.returncode == 0, r.stderr
    assert site.requests == ["/subjects/07/07_02.amc", "/subjects/07/07_09.amc"]


def test_fetch_removes_what_a_killed_fetch_left(site, tmp_path):
    d = tmp_path / "dest" / "cmu" / "07"
    d.mkdir(parents=True)
    stale, fresh = d / ".07_01.amc.abc123.part", d / ".07_01.amc.def456.part"
    stale.write_text("half a file")
    fresh.write_text("another fetch, still running")
    os.utime(stale, (1e9, 1e9))
    r = _fetch(site.base_url, tmp_path / "dest", "--trials", "07_01")
    assert r.returncode == 0, r.stderr
    assert not stale.exists() and fresh.exists()


def test_fetch_404_is_a_clear_error_and_leaves_no_file(site, tmp_path):
    dest = tmp_path / "dest"
    r = _fetch(site.base_url, dest, "--subjects", "07", "--trials", "07_99", "07_01")
    assert r.returncode == 2
    assert f"{site.base_url}/07/07_99.amc: HTTP 404" in r.stderr
    assert "lacuna: error: 1 of 3 files not fetched" in r.stderr
    assert "Traceback" not in r.stderr
    assert not (dest / "cmu" / "07" / "07_99.amc").exists()
    assert (dest / "cmu" / "07" / "07_01.amc").exists()  # the others still arrive
    assert _leftovers(dest) == []


def test_fetch_rejects_a_truncated_response(site, tmp_path):
    site.truncate.add("/subjects/07/07_02.amc")
    dest = tmp_path / "dest"
    r = _fetch(site.base_url, dest, "--trials", "07_02")
    assert r.returncode == 2
    assert "07_02.amc: connection closed after" in r.stderr and "(truncated download)" in r.stderr
    assert not (dest / "cmu" / "07" / "07_02.amc").exists()
    assert _leftovers(dest) == []


def test_fetch_rejects_an_amc_that_does_not_parse(site, data, tmp_path):
    # a complete HTTP response holding a file cut inside a frame
    text = (data / "cmu" / "07" / "07_09.amc").read_text()
    cut = text[: text.index("\n100\n") + len("\n100\n")] + "root 1 2 3 4 5 6\n"
    (Path(site.root) / "subjects" / "07" / "07_09.amc").write_text(cut)
    dest = tmp_path / "dest"
    r = _fetch(site.base_url, dest, "--trials", "07_09")
    assert r.returncode == 2
    assert "downloaded file does not parse, not kept" in r.stderr
    assert f"{site.base_url}/07/07_09.amc:" in r.stderr and "file ends inside frame 100" in r.stderr
    assert not (dest / "cmu" / "07" / "07_09.amc").exists()
    assert _leftovers(dest) == []


def test_fetch_rejects_an_asf_that_is_not_one_and_skips_its_trials(site, tmp_path):
    (Path(site.root) / "subjects" / "07" / "07.asf").write_text("<html><body>Service moved</body></html>\n")
    dest = tmp_path / "dest"
    r = _fetch(site.base_url, dest, "--trials", "07_01")
    assert r.returncode == 2
    assert "07.asf: no ':root' section" in r.stderr
    assert "07_01.amc: not fetched, the subject's ASF is unavailable" in r.stderr
    assert site.requests == ["/subjects/07/07.asf"]
    assert not (dest / "cmu").exists() or not any((dest / "cmu").rglob("*.a*"))


def test_fetch_times_out_and_gives_up(site, tmp_path):
    site.hang.add("/subjects/07/07.asf")
    dest = tmp_path / "dest"
    r = _fetch(site.base_url, dest, "--trials", "07_01", "07_02", "--timeout", "0.5")
    assert r.returncode == 2
    assert "07.asf: timed out after 0.5 s" in r.stderr
    assert "giving up on the 2 remaining files" in r.stderr
    assert site.requests == ["/subjects/07/07.asf"]


def test_fetch_connection_refused_is_clear(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    # nothing listens on the port now
    r = _fetch(f"http://127.0.0.1:{port}/subjects", tmp_path / "dest", "--trials", "07_01")
    assert r.returncode == 2
    assert f"http://127.0.0.1:{port}/subjects/07/07.asf: cannot connect" in r.stderr


def test_default_trials_are_those_of_the_shared_data(data, tmp_path):
    for s, trials in CMU_TRIALS.items():
        here = sorted(p.stem for p in (data / "cmu" / s).glob("*.amc"))
        assert trials == here, s
    items = plan(["7"], None, "http://h/subjects/", tmp_path)
    assert [i.url for i in items] == ["http://h/subjects/07/07.asf"] + [f"http://h/subjects/07/{t}.amc" for t in CMU_TRIALS["07"]]
    assert items[1].path == tmp_path / "cmu" / "07" / "07_01.amc"
    with pytest.raises(ValueError, match="no default trial list for subject 86"):
        plan(["86"], None, "http://h", tmp_path)
    with pytest.raises(ValueError, match="'7-1' is not a CMU trial name"):
        plan([], ["7-1"], "http://h", tmp_path)


def test_data_where_and_list(data, monkeypatch, capsys):
    monkeypatch.setenv("LACUNA_DATA", str(data))
    assert main(["data", "where"]) == 0
    out, err = capsys.readouterr()
    assert out.strip() == str(data) and "LACUNA_DATA" in err
    assert main(["data", "list"]) == 0
    out, _ = capsys.readouterr()
    assert "cmu/07  asf  4 trials: 07_01 07_02 07_09 07_10" in out


def test_data_where_without_data(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("LACUNA_DATA", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    import mocap.datasets as ds
    monkeypatch.setattr(ds, "_shared_candidates", list)  # pretend no checkout beside shared data
    assert main(["data", "where"]) == 1
    assert "lacuna data fetch cmu --subjects 07 35" in capsys.readouterr().err
