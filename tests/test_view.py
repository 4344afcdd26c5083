"""`lacuna view` end to end (issue 20, part 3): a real daemon process, a real client streaming a
real CMU take whose right arm drops out midway, `lacuna view` as its own process subscribed to
the daemon's PUB, and the page loaded in a real headless Chromium (the distribution's package,
driven over the DevTools pipe).  The assertions read the page's canvases pixel by pixel.
"""
from __future__ import annotations

import json
import os
import shutil
import time
import urllib.request

import numpy as np
import pytest
from waiting import wait_until

from clients import Client
from clients.configfile import free_port
from clients.harness import DaemonProcess
from clients.recording import RecordingWriter
from daemon import wire
from lacuna.cli import main
from mocap.baselines import HoldModel
from mocap.datasets import load_trial, trial_path
from view.headless import Browser, find_chromium
from view.process import ViewProcess

RIGHT_ARM = ("rclavicle", "rhumerus", "rradius", "rwrist", "rhand", "rfingers", "rthumb")
LEFT_ARM = ("lclavicle", "lhumerus", "lradius", "lwrist", "lhand", "lfingers", "lthumb")
PAGE_TIMEOUT_S = 60.0
PERIOD_S = 1 / 120.0


@pytest.fixture(scope="module")
def chromium():
    exe = find_chromium()
    if exe is None:
        if os.environ.get("CI") == "true":
            pytest.fail("CHROMIUM MISSING in CI (.ci/run installs Debian's chromium)")
        pytest.skip("CHROMIUM MISSING: apt-get install chromium (or set LACUNA_CHROMIUM)")
    return exe


@pytest.fixture(scope="module")
def daemon(tmp_path_factory, data):
    train = load_trial("07_02")
    d = tmp_path_factory.mktemp("view")
    hold = HoldModel.fit([train.frames], train.channels)
    hold.save(str(d / "hold.npz"))
    # a small HLM, for a stream with a style posterior and a gait phase
    assert main(["train", "hlm", "--styles", "2", "--cycle-frames", "60", "--iterations", "5", "--quiet",
                 str(trial_path("07_02")), str(trial_path("07_09")), "-o", str(d / "hlm.npz")]) == 0
    proc = DaemonProcess({"hold": str(d / "hold.npz"), "hlm": str(d / "hlm.npz")}, "hold", workdir=str(d / "daemon"), daemon={"budget_ms": 200.0},
                         zmq={"pub": f"tcp://127.0.0.1:{free_port()}"})
    proc.start()
    proc.hold = hold
    yield proc
    proc.stop()


def _state_when(url: str, ok, what: str) -> dict:
    """The view's state once ``ok(state)`` holds (polled; fails after PAGE_TIMEOUT_S naming ``what``)."""
    def look() -> dict | None:
        st = _state(url)
        return st if ok(st) else None
    return wait_until(look, PAGE_TIMEOUT_S, what, 0.05)


def _stream_until(clients: list[Client], take, k: int, observed, until) -> int:
    """Send frames k, k+1, ... of every client's stream at 120 Hz (wall-clock capture times) until
    ``until(k)``; returns the next k."""
    t0 = time.perf_counter()
    n = 0
    while not until(k):
        due = t0 + n * PERIOD_S
        while time.perf_counter() < due:
            time.sleep(0.0005)  # (pacing, not waiting: the streams run at 120 Hz)
        for c in clients:
            msg = c.fill(take.frames[k % take.n_frames], observed, seq=k)
            assert isinstance(msg, wire.FillMsg), msg
        k += 1
        n += 1
    return k


def _page_joints(b: Browser, sid: str, seq: int) -> list[dict]:
    b.wait_for(f"(lacunaView.joints({json.dumps(sid)}) || [{{}}])[0].seq === {seq}", PAGE_TIMEOUT_S)
    # one more animation frame, so the canvases hold what joints() describes
    b.evaluate("new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
    js = b.evaluate(f"lacunaView.joints({json.dumps(sid)})")
    for j in js:
        j["pixel"] = b.evaluate(f"lacunaView.pixel({json.dumps(sid)}, {j['px']['front'][0]}, {j['px']['front'][1]})")[:3]
    return js


def _close(a, b, tol=3) -> bool:
    return max(abs(x - y) for x, y in zip(a, b)) <= tol


def test_view_page_colours_the_joints_of_a_group_that_drops_out(daemon, chromium, tmp_path):
    take = load_trial("07_01")
    sid = "performer-1"
    C = len(take.channels)
    arm = np.array([c.split(".")[0] in RIGHT_ARM for c in take.channels])
    assert arm.sum() >= 7
    with ViewProcess(["--connect", daemon.zmq_opts["pub"], "--skeleton-file", str(trial_path("07_01")),
                      "--rate", "30"]) as view, Browser(chromium) as b, \
            Client(daemon.endpoint, sid, channels=list(take.channels)) as c, \
            Client(daemon.endpoint, "performer-2", channels=list(take.channels), model="hlm") as c2:
        b.goto(view.url)
        b.wait_for("window.lacunaView && lacunaView.state.connected", PAGE_TIMEOUT_S)
        c.hello()
        assert c2.hello().model == "hlm"
        # 1. everything observed: stream until the page has drawn the stream (the view's SUB
        #    joins the PUB some time after it starts), then stop and let it draw the last frame
        seen = lambda k: k >= 60 and b.evaluate(f"!!lacunaView.joints({json.dumps(sid)})")  # noqa: E731
        k = _stream_until([c, c2], take, 0, np.ones(C, bool), lambda k: k % 12 == 0 and seen(k))
        before = _page_joints(b, sid, k - 1)
        b.screenshot(str(tmp_path / "view_before.png"))
        observed_rgb = b.evaluate("lacunaView.colourOf(-1)")
        names = [j["name"] for j in before]
        ra = [i for i, n in enumerate(names) if n in RIGHT_ARM]
        la = [i for i, n in enumerate(names) if n in LEFT_ARM]
        assert len(ra) == 7 and len(la) == 7
        for i in ra + la:
            assert before[i]["fill"] == -1 and before[i]["rgb"] == observed_rgb, before[i]
            assert _close(before[i]["pixel"], observed_rgb), (names[i], before[i]["pixel"])
        # 2. the right arm drops out for half a second: the daemon fills it
        obs = ~arm
        k_end = k + 60
        k = _stream_until([c, c2], take, k, obs, lambda k: k >= k_end)
        after = _page_joints(b, sid, k - 1)
        _page_joints(b, "performer-2", k - 1)
        shot = b.screenshot(str(tmp_path / "view_after.png"))
        # each right-arm joint is filled with the hold model's std: the largest over its channels
        std = daemon.hold.std_
        for i in ra:
            cols = [q for q, ch in enumerate(take.channels) if ch.split(".")[0] == names[i]]
            assert after[i]["fill"] == pytest.approx(float(np.max(std[cols])), abs=0.01), names[i]
            assert after[i]["rgb"] == b.evaluate(f"lacunaView.colourOf({after[i]['fill']})")
            assert not _close(after[i]["pixel"], observed_rgb, 20), (names[i], after[i]["pixel"])
        # what is drawn there is on the std colour scale (the arm's joints overlap in the front
        # view, and a joint's centre may be an anti-aliased edge of its neighbour)
        scale = b.evaluate("Array.from({length: 201}, (_, i) => lacunaView.colourOf(i * lacunaView.state.meta.std_max / 200))")
        for i in ra:
            assert min(max(abs(x - y) for x, y in zip(after[i]["pixel"], c)) for c in scale) <= 12, \
                (names[i], after[i]["pixel"])
        assert sum(_close(after[i]["pixel"], after[i]["rgb"]) for i in ra) >= 4
        # the other arm is still observed, drawn plain
        for i in la:
            assert after[i]["fill"] == -1 and _close(after[i]["pixel"], observed_rgb), names[i]
        # every view canvas has a skeleton on it, and the latency plot was drawn from wall-clock
        # capture times (the client stamps t with time.time())
        lit = b.evaluate("""['performer-1', 'performer-2'].flatMap(id => ['front', 'side', 'top'].map(v => {
            const [x, y, w, h] = lacunaView.region(id, v);
            const d = document.getElementById('board').getContext('2d').getImageData(x, y, w, h).data; let n = 0;
            for (let i = 0; i < d.length; i += 4) if (d[i] > 100 || d[i+1] > 100) n++; return n; }))""")
        assert len(lit) == 6 and min(lit) > 50, lit
        # the HLM stream's style posterior and gait phase reached the page and were drawn
        last = b.evaluate("lacunaView.state.streams['performer-2'].last")
        assert len(last["style"]) == 2 and abs(sum(last["style"]) - 1) < 1e-3 and 0 <= last["phase"] < 1
        assert b.evaluate("lacunaView.state.streams['performer-1'].last.style") is None
        bars = b.evaluate("""(() => { const [x, y, w] = lacunaView.region('performer-2', 'style');
            const d = document.getElementById('board').getContext('2d').getImageData(x, y, w, 56).data; let n = 0;
            for (let i = 0; i < d.length; i += 4) if (d[i] === 0x4f && d[i+1] === 0xc3 && d[i+2] === 0xf7) n++;
            return n; })()""")
        assert bars > 20, bars  # the most probable style's bar, in its colour
        stats = b.wait_for(f"(lacunaView.state.streams[{json.dumps(sid)}] || {{}}).stats", PAGE_TIMEOUT_S)
        assert stats["proc_p50_ms"] >= 0 and stats["age_p50_ms"] > 0
        # the stream's text line catches up with the last frame (it is redrawn twice a second)
        b.wait_for(f"lacunaView.text({json.dumps(sid)}).includes('seq {k - 1} ')", PAGE_TIMEOUT_S)
        assert b.console_errors() == []
    assert os.path.getsize(shot) > 10_000
    keep = os.environ.get("LACUNA_VIEW_SHOTS")
    if keep:
        os.makedirs(keep, exist_ok=True)
        for n in ("view_before.png", "view_after.png"):
            shutil.copy(tmp_path / n, os.path.join(keep, n))


def _state(url: str) -> dict:
    with urllib.request.urlopen(url + "state.json", timeout=5) as r:
        return json.loads(r.read())


def test_view_plays_a_recording(data, tmp_path):
    """--play an .lrec: the recorded fills reach the page's feed with the joints they filled."""
    take = load_trial("07_01").slice(0, 120)
    leg = np.array([c.split(".")[0] in ("lfemur", "ltibia") for c in take.channels])
    path = tmp_path / "take.lrec"
    with RecordingWriter(path, take.channels, take.fps, "rec-1", "test") as w:
        for k in range(take.n_frames):
            w.write(k, k / take.fps, np.where(leg, np.nan, take.frames[k]), ~leg,
                    wire.FillMsg("rec-1", k, k / take.fps, take.frames[k].astype(np.float32), leg,
                                 np.where(leg, 3.5, 0).astype(np.float32), "ok", "m", 100))
    with ViewProcess(["--play", str(path), "--speed", "4", "--loop", "--skeleton-file", str(trial_path("07_01"))]) as v:
        st = _state_when(v.url, lambda st: st["update"] and st["update"]["streams"] and "pos" in st["update"]["streams"][0],
                         "a drawn frame (positions) in the view's state")
    meta, upd = st["meta"], st["update"]["streams"][0]
    assert meta["mode"] == "play" and upd["id"] == "rec-1" and upd["proc_ms"] is None
    joints = meta["skeleton"]["joints"]
    fill = dict(zip(joints, upd["fill"]))
    assert fill["lfemur"] == 3.5 and fill["ltibia"] == 3.5
    assert all(v == -1 for j, v in fill.items() if j not in ("lfemur", "ltibia"))
    assert len(upd["pos"]) == 3 * len(joints) and all(np.isfinite(upd["pos"]))


def test_view_bad_input_is_one_line_error(tmp_path, capsys, data):
    assert main(["view", "--play", str(tmp_path / "none.lrec"), "--skeleton-file", str(trial_path("07_01"))]) == 2
    assert "--play" in capsys.readouterr().err
    rec = tmp_path / "r.lrec"
    with RecordingWriter(rec, ["root.tx"], 120.0) as w:
        w.write(0, 0.0, np.zeros(1))
    assert main(["view", "--play", str(rec)]) == 2
    assert "--skeleton-file is needed" in capsys.readouterr().err
    assert main(["view", "--connect", "tcp://127.0.0.1:1", "--skeleton-file", str(tmp_path / "x.bvh")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main(["view", "--connect", "tcp://127.0.0.1:1", "--speed", "2",
                 "--skeleton-file", str(trial_path("07_01"))]) == 2
    assert "apply to --play" in capsys.readouterr().err
    assert main(["view", "--connect", "tcp://127.0.0.1:1", "--fps", "0",
                 "--skeleton-file", str(trial_path("07_01"))]) == 2
    assert "--fps and --max-dpr must be > 0" in capsys.readouterr().err


def test_view_plays_a_bvh_take_on_its_own_skeleton(data):
    """A played BVH is its own skeleton: the page gets its joints (End Sites included) at the
    positions mocap.fk gives for the frame played, turned y-up if the file is not."""
    from mocap.fk import Kinematics
    from mocap.io import read_motion

    path = os.path.join(str(data), "bvh", "09_11.bvh")
    m = read_motion(path)
    kin = Kinematics.from_motion(m)
    with ViewProcess(["--play", path, "--loop"]) as v:
        st = _state_when(v.url, lambda st: st["update"] and st["update"]["streams"] and "pos" in st["update"]["streams"][0],
                         "a drawn frame (positions) in the view's state")
    assert st["meta"]["skeleton"]["joints"] == kin.joints
    upd = st["update"]["streams"][0]
    from view.feed import TO_Y_UP

    want = kin.position(m.frames[upd["seq"]]) @ TO_Y_UP[kin.up_axis].T
    assert np.abs(np.array(upd["pos"]).reshape(-1, 3) - want).max() < 1e-3


def test_view_draws_on_the_skeleton_a_model_file_was_trained_on(daemon, capsys):
    """Without --skeleton-file, a model file given to --channels that carries its training
    skeleton (lacuna train writes it) is enough; one without (the hold model here) is refused."""
    from mocap.fk import Kinematics

    hlm = str(daemon.workdir.parent / "hlm.npz")
    with ViewProcess(["--connect", daemon.zmq_opts["pub"], "--channels", hlm]) as v:
        st = _state_when(v.url, lambda st: "skeleton" in st["meta"], "the skeleton in the view's meta")
    assert st["meta"]["skeleton"]["joints"] == Kinematics.from_motion(load_trial("07_02")).joints
    assert "training skeleton" in st["meta"]["skeleton"]["source"]
    hold = str(daemon.workdir.parent / "hold.npz")
    assert main(["view", "--connect", daemon.zmq_opts["pub"], "--channels", hold]) == 2
    assert "--skeleton-file is needed" in capsys.readouterr().err
