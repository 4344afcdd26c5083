"""What the live page draws, and when (issue 20: the page costs the capture box less): at most
its fps cap, only when a new frame came, nothing while its tab is hidden.  A real `lacuna view`
process plays a real CMU take; the page runs in a real headless Chromium.  Everything is counted
by the page itself (received updates, drawn frames, the animation-frame times of its draws): no
wall-clock figure is asserted.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from clients.recording import RecordingWriter
from daemon import wire
from mocap.datasets import load_trial, trial_path
from tests.test_view import chromium  # noqa: F401
from view.headless import Browser
from view.process import ViewProcess

pytestmark = pytest.mark.realdata
TIMEOUT_S = 60.0
SID = "rec-1"


@pytest.fixture(scope="module")
def recording(data, tmp_path_factory):
    """CMU 07_01's first second as a recording, its left leg filled (std 3.5 deg)."""
    take = load_trial("07_01").slice(0, 120)
    leg = np.array([c.split(".")[0] in ("lfemur", "ltibia") for c in take.channels])
    path = tmp_path_factory.mktemp("cap") / "take.lrec"
    with RecordingWriter(path, take.channels, take.fps, SID, "test") as w:
        for k in range(take.n_frames):
            w.write(k, k / take.fps, np.where(leg, np.nan, take.frames[k]), ~leg,
                    wire.FillMsg(SID, k, k / take.fps, take.frames[k].astype(np.float32), leg,
                                 np.where(leg, 3.5, 0).astype(np.float32), "ok", "m", 100))
    return path


def _counts(b: Browser) -> dict:
    return b.evaluate("""(() => { const s = lacunaView.state, r = s.streams['rec-1'];
        return {updates: s.updates, draws: s.draws, held: s.held, raf: s.raf, drawT: s.drawT.slice(),
                hidden: s.hiddenUpdates, skeleton: r ? (r.draws || 0) : 0, seq: r && r.pose ? r.pose.seq : -1,
                fps: s.fps}; })()""")


def _after_updates(b: Browser, n: int) -> None:
    """Until the page has received ``n`` more updates than now (its own counter)."""
    u0 = b.evaluate("lacunaView.state.updates")
    b.wait_for(f"lacunaView.state.updates >= {u0 + n}", TIMEOUT_S)


def test_the_page_draws_at_most_its_fps_cap_and_nothing_while_hidden(recording, chromium):  # noqa: F811
    # updates come at 60 a second, the page may draw 10: most updates must wait or be skipped
    with ViewProcess(["--play", str(recording), "--loop", "--skeleton-file", str(trial_path("07_01")),
                      "--rate", "60", "--fps", "30"]) as view, Browser(chromium) as b:
        b.goto(view.url + "?fps=10")  # the page's address overrides the view's --fps
        b.wait_for(f"(lacunaView.state.streams[{json.dumps(SID)}] || {{}}).pose", TIMEOUT_S)
        c0 = _counts(b)
        assert c0["fps"] == 10
        _after_updates(b, 60)
        c1 = _counts(b)
        drawn = c1["skeleton"] - c0["skeleton"]
        assert 1 <= drawn <= c1["updates"] - c0["updates"]
        # every two draws at least 1000/10 ms apart on the page's animation-frame clock (less the
        # cap's 2 ms of vsync slack), and the cap did hold frames back (more came than it drew)
        gaps = np.diff([t for t in c1["drawT"] if t > (c0["drawT"] or [-1.0])[-1]])
        assert gaps.size >= 1 and gaps.min() >= 100.0 - 2.0, gaps
        assert c1["held"] > c0["held"]
        assert b.evaluate("document.visibilityState") == "visible"

        # another tab in front: updates still arrive, nothing is drawn
        b.hide()
        b.wait_for("document.hidden", TIMEOUT_S)
        h0 = _counts(b)
        _after_updates(b, 30)
        h1 = _counts(b)
        assert h1["hidden"] - h0["hidden"] >= 30
        assert h1["draws"] == h0["draws"] and h1["skeleton"] == h0["skeleton"]

        # back in front: it draws the newest frame again
        b.show()
        b.wait_for(f"!document.hidden && lacunaView.state.streams[{json.dumps(SID)}].draws > {h1['skeleton']}",
                   TIMEOUT_S)
        assert b.console_errors() == []


def test_a_page_opened_after_the_take_ended_still_shows_its_last_pose(recording, chromium):  # noqa: F811
    """The view publishes each tick's new frames, and once a second a tick of stats alone; a page that
    opened after the last frame and after such a tick got only the stats, and no stream to draw.  Now
    a page gets every stream's newest frame first (the snapshot), whenever it opens."""
    from tests.test_view import _state_when

    with ViewProcess(["--play", str(recording), "--skeleton-file", str(trial_path("07_01"))]) as view:
        def last(st):
            return any(d["id"] == SID and d["seq"] == 119 for d in (st["update"] or {}).get("streams", []))
        t_last = _state_when(view.url, last, "the take's last frame in the view")["update"]["time"]
        # a later update: the take has ended, so it is a tick of stats alone (played files have no latency)
        _state_when(view.url, lambda st: (st["update"] or {}).get("time", 0) > t_last, "a tick after the take ended")
        with Browser(chromium) as b:
            b.goto(view.url)
            b.wait_for(f"(lacunaView.state.streams[{json.dumps(SID)}] || {{}}).pose.seq === 119", TIMEOUT_S)
            assert b.console_errors() == []


def test_the_page_draws_a_stream_only_when_a_new_frame_came(recording, chromium):  # noqa: F811
    # played once: after its last frame (seq 119) no frame comes, and the skeleton is not redrawn
    # however many animation frames pass (the page's counter of them)
    with ViewProcess(["--play", str(recording), "--skeleton-file", str(trial_path("07_01"))]) as view, \
            Browser(chromium) as b:
        b.goto(view.url)
        b.wait_for(f"(lacunaView.state.streams[{json.dumps(SID)}] || {{}}).pose.seq === 119", TIMEOUT_S)
        b.wait_for(f"lacunaView.state.streams[{json.dumps(SID)}].dirty === false", TIMEOUT_S)
        c0 = _counts(b)
        b.wait_for(f"lacunaView.state.raf >= {c0['raf'] + 60}", TIMEOUT_S)
        c1 = _counts(b)
        assert c1["skeleton"] == c0["skeleton"] >= 1
        assert c1["seq"] == 119
