"""The view served by the daemon itself (``[metrics] view = true``, view/in_daemon.py): a real
daemon process, a real client streaming CMU 07_01 whose right arm drops out, the page loaded
from the daemon's metrics port in a real headless Chromium; and feeds that do not read are
closed while the daemon serves on.
"""
from __future__ import annotations

import json
import socket
import urllib.request

import numpy as np
import pytest

from clients import Client
from clients.configfile import free_port
from clients.control import control
from clients.harness import DaemonProcess
from daemon import wire
from lacuna.cli import main
from mocap.baselines import HoldModel
from mocap.datasets import load_trial, trial_path
from tests.test_view import RIGHT_ARM, _close, _page_joints, _stream_until, chromium  # noqa: F401
from tests.waiting import wait_until
from view.headless import Browser

pytestmark = pytest.mark.realdata
TINY_HLM = ["--styles", "1", "--restarts", "1", "--iterations", "3", "-N", "120", "-q"]


@pytest.fixture(scope="module")
def served(tmp_path_factory, data):
    d = tmp_path_factory.mktemp("view-daemon")
    train = load_trial("07_02")
    hold = HoldModel.fit([train.frames], train.channels)
    hold.save(str(d / "hold.npz"))
    # the default model carries the training skeleton the page draws on (a hold model has none)
    assert main(["train", "hlm", str(trial_path("07_02")), "-o", str(d / "hlm.npz"), *TINY_HLM]) == 0
    http = free_port()
    proc = DaemonProcess({"hlm": str(d / "hlm.npz"), "hold": str(d / "hold.npz")}, "hlm", workdir=str(d / "daemon"),
                         daemon={"budget_ms": 200.0}, zmq={"pub": f"tcp://127.0.0.1:{free_port()}"},
                         metrics={"http": f"127.0.0.1:{http}", "view": True})
    proc.start()
    proc.hold, proc.http = hold, f"http://127.0.0.1:{http}"
    yield proc
    proc.stop()


def _http_info(d) -> dict:
    return control(d.endpoint, "status").result["metrics_http"]


def test_the_daemon_serves_the_view_page_that_colours_a_dropped_group(served, chromium):  # noqa: F811
    d = served
    take = load_trial("07_01")
    sid = "performer-1"
    C = len(take.channels)
    arm = np.array([c.split(".")[0] in RIGHT_ARM for c in take.channels])
    assert urllib.request.urlopen(d.http + "/metrics", timeout=10).status == 200  # metrics as before
    with Browser(chromium) as b, Client(d.endpoint, sid, channels=list(take.channels), model="hold") as c:
        b.goto(d.http + "/view")  # redirected to /view/, whose files are relative to it
        b.wait_for("window.lacunaView && lacunaView.state.connected", 60)
        c.hello()
        seen = lambda k: k >= 60 and b.evaluate(f"!!lacunaView.joints({json.dumps(sid)})")  # noqa: E731
        k = _stream_until([c], take, 0, np.ones(C, bool), lambda k: k % 12 == 0 and seen(k))
        before = _page_joints(b, sid, k - 1)
        observed = b.evaluate("lacunaView.colourOf(-1)")
        names = [j["name"] for j in before]
        ra = [i for i, n in enumerate(names) if n in RIGHT_ARM]
        assert len(ra) == 7
        assert all(before[i]["fill"] == -1 and _close(before[i]["pixel"], observed) for i in ra)
        k_end = k + 60
        k = _stream_until([c], take, k, ~arm, lambda k: k >= k_end)
        after = _page_joints(b, sid, k - 1)
        std = d.hold.std_
        for i in ra:
            cols = [q for q, ch in enumerate(take.channels) if ch.split(".")[0] == names[i]]
            assert after[i]["fill"] == pytest.approx(float(np.max(std[cols])), abs=0.01), names[i]
            assert not _close(after[i]["pixel"], observed, 20), (names[i], after[i]["pixel"])
        assert sum(_close(after[i]["pixel"], after[i]["rgb"]) for i in ra) >= 4
        assert "daemon's PUB" in b.evaluate("document.getElementById('source').textContent")
    info = _http_info(d)
    assert info["view_pages"] >= 1 and info["view"]["decoded"] > 0


def test_a_feed_that_does_not_read_is_closed_and_the_daemon_serves_on(served):
    d = served
    host, port = d.http[len("http://"):].split(":")
    take = load_trial("07_01")
    dropped0 = _http_info(d)["view_dropped"]
    # a page that asks for the feed and never reads it (a tiny receive buffer: the backlog grows in the daemon)
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.connect((host, int(port)))
    s.sendall(b"GET /view/events HTTP/1.0\r\n\r\n")
    extra = []
    try:
        # four feeds at most: of five more, at least one is refused 503
        for _ in range(5):
            e = socket.create_connection((host, int(port)), timeout=10)
            e.sendall(b"GET /view/events HTTP/1.0\r\n\r\n")
            extra.append(e)
        heads = [e.recv(64) for e in extra]
        assert any(h.startswith(b"HTTP/1.0 503") for h in heads), heads
        for e in extra:
            e.close()
        with Client(d.endpoint, "flood", channels=list(take.channels), positions=False, model="hold") as c:
            c.hello()
            k = 0

            def dropped() -> bool:
                nonlocal k
                for _ in range(24):  # frames keep the feed's updates (and its backlog) coming
                    m = c.fill(take.frames[k % take.n_frames], seq=k)
                    assert isinstance(m, wire.FillMsg) and m.status == "ok", m
                    k += 1
                return _http_info(d)["view_dropped"] > dropped0

            wait_until(dropped, 120, what="the non-reading feed closed")
            assert c.fill(take.frames[0], seq=k).status == "ok"  # the daemon serves on
    finally:
        s.close()
