"""``default`` (blend/): trained on real takes, checked on held-out ones; the model file; the CLI."""
from __future__ import annotations

import numpy as np
import pytest

from blend.fit import occlusion
from blend.model import DefaultModel, wrap
from blend.train import train_model
from lacuna import modelfile, registry
from lacuna.cli import main as cli_main
from mocap import splits
from mocap.baselines import HoldModel
from mocap.representation import is_angle

pytestmark = pytest.mark.realdata

TRAIN = ["07_02", "35_01", "35_06", "walking_13", "walking_14", "basketball_1", "soccer_1", "basketball_signal_1"]


@pytest.fixture(scope="module")
def small(data):
    """``default`` as shipped: the Gaussian on the TRAIN split (a second), the weights chosen on validation."""
    seqs = [splits.load_take(t).frames for t in splits.TRAIN]
    ch = splits.load_take(splits.TRAIN[0]).channels
    return train_model(seqs, ch, splits.TRAIN), HoldModel.fit(seqs, ch)


def _erased(truth, fill, obs, channels):
    ang = np.array([is_angle(c) for c in channels])
    e = wrap(fill - truth)
    return e[~obs & ang[None]]


def test_first_erased_frame_starts_where_the_performer_was(small):
    """Every gap of a validation walk (left leg, 0.3 s every 0.6 s): the first filled frame is
    within 2x the truth's own step, and the first 100 ms beat hold."""
    model, hold = small
    truth = splits.load_take("walking_20").frames
    ch = model.channels
    cols = np.array([c.split(".")[0] in ("lfemur", "ltibia", "lfoot", "ltoes") for c in ch])
    obs = np.ones(truth.shape, bool)
    starts = list(range(60, truth.shape[0] - 40, 72))
    for s in starts:
        obs[s:s + 36, cols] = False
    given = np.where(obs, truth, np.nan)
    fill, std = model.fill_offline(given, obs)
    hfill, _ = hold.fill_offline(given, obs)
    first = np.array(starts)
    err1 = np.abs(wrap(fill[np.ix_(first, np.flatnonzero(cols))] - truth[np.ix_(first, np.flatnonzero(cols))]))
    step = np.abs(wrap(truth[np.ix_(first, np.flatnonzero(cols))] - truth[np.ix_(first - 1, np.flatnonzero(cols))]))
    assert np.median(err1) <= 2 * np.median(step)
    early = np.zeros(truth.shape, bool)
    for s in starts:
        early[s:s + 12, cols] = True
    e_def = wrap(fill - truth)[early]
    e_hold = wrap(hfill - truth)[early]
    assert np.sqrt(np.mean(e_def**2)) < np.sqrt(np.mean(e_hold**2))
    assert (std[~obs] > 0).all() and (std[obs] == 0).all()
    np.testing.assert_array_equal(fill[obs], truth[obs])  # observed values come back exactly


@pytest.mark.parametrize("take", ["walking_27", "soccer_5", "basketball_signal_5"])
def test_not_worse_than_hold_and_calibrated_on_held_out_takes(small, take):
    """TEST takes (a walk of another performer, non-locomotion), which neither the model's training
    nor the shipped weights' fit (validation takes, seeds 100-102) saw, with the gaps-like occlusion."""
    model, hold = small
    truth = splits.load_take(take).frames
    obs, _ = occlusion(take, truth.shape[0], model.channels, 120.0, seed=0)
    given = np.where(obs, truth, np.nan)
    fill, std = model.fill_offline(given, obs)
    hfill, _ = hold.fill_offline(given, obs)
    ang = np.array([c.split(".")[0] != "root" and is_angle(c) for c in model.channels])
    m = ~obs & ang[None]
    e, eh = wrap(fill - truth)[m], wrap(hfill - truth)[m]
    assert np.sqrt(np.mean(e**2)) <= np.sqrt(np.mean(eh**2))
    share = np.mean(np.abs(e) <= 2 * std[m])
    assert 0.85 <= share <= 0.995, share


def test_weights_fitted_on_given_takes_beat_hold(data):
    """The calibration path: weights fitted on two held-out takes are not all zero and beat hold on a
    third take they were not fitted on."""
    seqs = [splits.load_take(t).frames for t in TRAIN[:4]]
    ch = splits.load_take(TRAIN[0]).channels
    cal = [(t, splits.load_take(t).frames, "walk") for t in ("07_10", "walking_21")]
    model = train_model(seqs, ch, TRAIN[:4], calibrate=cal)
    assert np.abs(model.weights.wv).max() > 0.05 and np.abs(model.weights.wr).max() > 0.05
    assert model.meta["calibration"]["data"] == ["07_10", "walking_21"]
    truth = splits.load_take("walking_20").frames
    obs, _ = occlusion("walking_20", truth.shape[0], ch, 120.0, seed=0)
    given = np.where(obs, truth, np.nan)
    e = wrap(model.fill_offline(given, obs)[0] - truth)[~obs]
    eh = wrap(HoldModel.fit(seqs, ch).fill_offline(given, obs)[0] - truth)[~obs]
    assert np.mean(e**2) < np.mean(eh**2)


def test_fit_keeps_the_root_angles_within_hold_in_every_activity_and_bin(small):
    """The root's own Euler angles get cells of their own in the fit: on the takes the weights are
    fitted on, no (activity, time since onset) cell of the root angles is worse than hold, and
    neither is any cell of the other angle groups pooled (the fit's promise, checked on its output);
    the root's translation is fitted unboosted and beats hold over all."""
    from blend.fit import CELL_EDGES, _hat, collect, fit_weights
    from blend.model import ROOT_POS

    model, _ = small
    takes = [(t, splits.load_take(t).frames, splits.ACTIVITY[t]) for t in splits.VALIDATION]
    data = collect(model, takes, (100,))
    w = fit_weights(model, data)
    t = data["k"] / model.settings.fps
    Phi, g, H = _hat(model, t), data["g"], data["H"]
    lv, lr = data["lam"][:, None], data["lamr"][:, None]  # the guard's scales, as the stream had them
    fill = H + np.sum(Phi * (lv * (w.wv[g] * (data["V"] - H)[:, None] + w.wl[g] * (data["W"] - H)[:, None])
                             + lr * (w.wr[g] * data["weak"][:, None] + w.wg[g] * data["gate"][:, None]) * (data["R"] - H)[:, None]), 1)
    e2, h2 = (data["y"] - fill) ** 2, (data["y"] - H) ** 2
    bins = np.searchsorted(CELL_EDGES, t, side="right")
    checked = 0
    for a in np.unique(data["act"]):
        for b in np.unique(bins):
            for sel in ((data["act"] == a) & (bins == b) & (g == 0), (data["act"] == a) & (bins == b) & (g != 0) & (g != ROOT_POS)):
                if sel.sum() >= 200:  # the root of one activity in one bin: a handful of gaps below that
                    # within 5%: the weights of a group are shared by the activities and smoothed across
                    # knots, so a boosted cell can stay a little above hold
                    assert e2[sel].sum() <= 1.05 * h2[sel].sum(), (data["activities"][a], b, bool(g[sel][0] == 0),
                                                                   e2[sel].sum() / h2[sel].sum())
                    checked += 1
    assert checked >= 30
    rp = g == ROOT_POS
    assert e2[rp].sum() < h2[rp].sum()
    assert np.abs(w.wv[0]).max() + np.abs(w.wl[0]).max() > 0  # the root is not simply held


def test_model_file_round_trip_gives_identical_fills_and_bad_files_are_refused(small, tmp_path):
    model, _ = small
    p = tmp_path / "default.npz"
    model.save(str(p))
    again = modelfile.load_model(str(p))
    assert isinstance(again, DefaultModel) and again.method == "default"
    truth = splits.load_take("soccer_4").frames[:400]
    obs, _ = occlusion("soccer_4", 400, model.channels, 120.0, seed=101)
    given = np.where(obs, truth, np.nan)
    a, sa = model.fill_offline(given, obs)
    b, sb = again.fill_offline(given, obs)
    assert np.array_equal(a, b) and np.array_equal(sa, sb)
    raw = p.read_bytes()
    bad = tmp_path / "cut.npz"
    bad.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(modelfile.ModelFileError, match="truncated or corrupt"):
        modelfile.load_model(str(bad))
    meta, arrays = modelfile.load_arrays(str(p))
    arrays["cov"] = arrays["cov"][:-1]
    modelfile.save_arrays(str(tmp_path / "shape.npz"), meta, arrays)
    with pytest.raises(modelfile.ModelFileError, match="'cov' has shape"):
        modelfile.load_model(str(tmp_path / "shape.npz"))


def test_batched_step_matches_one_stream_at_a_time(small):
    model, _ = small
    truth = splits.load_take("07_10").frames[:200]
    masks = [occlusion(f"s{i}", 200, model.channels, 120.0, seed=i)[0] for i in range(3)]
    solo = [model.stream() for _ in masks]
    batch = [model.stream() for _ in masks]
    for t in range(200):
        O = np.stack([m[t] for m in masks])
        F = np.where(O, truth[t][None], np.nan)
        fills = model.step_batch(batch, F, O)
        for i in range(3):
            f = solo[i].step(F[i], O[i])
            assert np.array_equal(f.frame, fills[i].frame) and np.array_equal(f.std, fills[i].std)
    assert solo[0].predict().filled.all()  # a frame that never arrived: everything is filled


@pytest.mark.parametrize("changes", [{"gate_rho": 0.7}, {"gate_rho": 0.7, "vel_shrink": 4.0}, {"gate_rho": 0.7, "vel_shrink": 0.0}])
def test_compiled_step_matches_the_numpy_step_with_the_gate_on(small, changes):
    """blend.fast against DefaultState.step_numpy on real motion, with the regression gate active (and the
    onset velocity's shrink on and off)."""
    from lacuna import jit

    if not jit.enabled():
        pytest.skip("numba unavailable or LACUNA_NO_JIT set: only the numpy step runs here")
    model, _ = small
    gated = model.with_settings(**changes)
    for take in ("walking_23", "basketball_4"):
        truth = splits.load_take(take).frames[:300]
        obs, _ = occlusion(take, 300, model.channels, 120.0, seed=102)
        a, b = gated.stream(), gated.stream()
        for t in range(300):
            fr = np.where(obs[t], truth[t], np.nan)
            fa = a.step(fr, obs[t])
            fb = b.step_numpy(fr.copy(), obs[t].copy())
            np.testing.assert_allclose(fa.frame, fb.frame, rtol=0, atol=1e-9)
            np.testing.assert_allclose(fa.std, fb.std, rtol=0, atol=1e-9)
        assert (b.ER > 0).any() and np.isfinite(b.gate(np.arange(len(b.ER)))).all()


def test_registered_and_trainable_from_the_command_line(data, tmp_path, capsys):
    assert "default" in registry.methods() and registry.get_method("default").causal
    files = [str(splits.take_path(t)) for t in ("07_02", "walking_13")]
    out = tmp_path / "d.npz"
    assert cli_main(["train", "default-blend", *files, "-o", str(out)]) == 0
    assert modelfile.load_model(str(out)).meta["training"]["data"] == ["07_02.amc", "walking_13.amc"]
    assert cli_main(["train", "default-blend", str(tmp_path / "missing.amc"), "-o", str(out)]) == 2
    assert "lacuna: error:" in capsys.readouterr().err


def test_daemon_serves_default_over_a_real_socket(small, tmp_path):
    """A real `lacuna serve` process loads the model file and answers frames with gaps the way the
    model does in-process (values travel as float32)."""
    import json

    import zmq

    from clients.harness import DaemonProcess
    from daemon import wire

    model, _ = small
    path = tmp_path / "default.npz"
    model.save(str(path))
    cfg = tmp_path / "lacuna.toml"
    cfg.write_text("\n".join(["[daemon]", "budget_ms = 250.0", "idle_timeout_s = 60", "max_gap_frames = 5",
                              'default_model = "default"', "[models.default]", f"file = {json.dumps(str(path))}",
                              "[zmq]", 'router = "tcp://127.0.0.1:*"', 'pub = "tcp://127.0.0.1:*"']) + "\n")
    d = DaemonProcess(str(cfg)).start()
    ctx = zmq.Context()
    s = ctx.socket(zmq.DEALER)
    s.setsockopt(zmq.LINGER, 0)
    try:
        s.connect(d.endpoints["router"])
        truth = splits.load_take("walking_21").frames[:120].astype(np.float32)
        obs = np.ones(truth.shape, bool)
        obs[40:100, 6:20] = False  # both legs drop out for half a second
        ref = model.stream()
        for t in range(truth.shape[0]):
            vals = np.where(obs[t], truth[t], np.nan).astype(np.float32)
            s.send(wire.encode(wire.Frame("p1", t, t / 120.0, vals, None)))
            assert s.poll(10000), "no answer from the daemon"
            m = wire.decode(s.recv_multipart()[-1], 64 << 20)
            want = ref.step(vals.astype(np.float64), obs[t])
            assert isinstance(m, wire.FillMsg) and m.model == "default" and m.seq == t
            np.testing.assert_array_equal(m.filled, ~obs[t])
            np.testing.assert_allclose(m.angles, want.frame.astype(np.float32), rtol=0, atol=1e-3)
    finally:
        s.close(0)
        ctx.term()
        d.stop()


def test_vel_shrink_extrapolates_a_ramp_and_not_a_jitter():
    """Settings.vel_shrink (bench/notebook/vshr-42.md): a channel moving at a steady rate keeps its whole
    velocity at a gap's onset (its second differences are 0); a still channel whose value jitters frame
    to frame gets little of its smoothed velocity; off (0) it is the smoothed velocity itself.  Both steps
    (numpy, compiled)."""
    from blend.model import Settings, Weights
    from lacuna import jit

    C = 2
    ch = ["lfemur.rx", "rfemur.rx"]
    s = Settings(lags_s=(0.05,), vel_s=0.05, vel_shrink=16.0)
    m = DefaultModel(ch, np.zeros(C), np.ones(C), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 0)), s, Weights.initial(),
                     {}, None, None)
    T = 240
    t = np.arange(T)
    x = np.stack([10.0 + 0.3 * t, 5.0 + 0.4 * (-1.0) ** t], 1)  # a ramp of 0.3 deg a frame; +-0.4 deg of jitter
    for shrink, check in ((16.0, True), (0.0, False)):
        mm = m.with_settings(vel_shrink=shrink)
        steps = ["step_numpy"] + (["step"] if jit.enabled() else [])
        for how in steps:
            st = mm.stream()
            for i in range(T):
                getattr(st, how)(x[i].copy(), np.ones(C, bool))
            raw = st.vel.copy()
            getattr(st, how)(np.array([np.nan, np.nan]), np.zeros(C, bool))  # both drop out
            assert abs(raw[0] - 0.3) < 1e-6 and abs(raw[1]) > 0.05, raw  # the smoothed velocities: the jitter's is not 0
            if check:
                assert st.v0[0] == raw[0]  # the ramp's is kept whole
                assert abs(st.v0[1]) < 0.1 * abs(raw[1]), (st.v0, raw)  # the jitter's is mostly not extrapolated (~3% of it)
            else:
                np.testing.assert_array_equal(st.v0, raw)


def test_vel_shrink_off_for_old_files_and_refused_when_malformed(small, tmp_path):
    """A model file written before vel_shrink loads with it off (its fills those of vel_shrink = 0); a
    negative or non-finite value in a file is refused by name."""
    model, _ = small
    p = tmp_path / "m.npz"
    model.with_settings(vel_shrink=4.0).save(str(p))
    meta, arrays = modelfile.load_arrays(str(p))
    assert type(model).load(str(p), meta, arrays).settings.vel_shrink == 4.0
    old_meta = {**meta, "settings": {k: v for k, v in meta["settings"].items() if k != "vel_shrink"}}
    old = type(model).load(str(p), old_meta, arrays)
    assert old.settings.vel_shrink == 0.0
    truth = splits.load_take("walking_27").frames[:400]
    obs, _ = occlusion("walking_27", truth.shape[0], model.channels, 120.0, seed=1)
    given = np.where(obs, truth, np.nan)
    np.testing.assert_array_equal(old.fill_offline(given, obs)[0], model.with_settings(vel_shrink=0.0).fill_offline(given, obs)[0])
    for bad in (-1.0, float("nan"), float("inf"), "4"):
        with pytest.raises(modelfile.ModelFileError, match="vel_shrink"):
            type(model).load(str(p), {**meta, "settings": {**meta["settings"], "vel_shrink": bad}}, arrays)


def _with(model, **over):
    from blend.model import DefaultModel, Settings

    s = Settings(**{**model.settings.__dict__, **over})
    return DefaultModel(model.channels, model.mean_, model.std_, model.reg_idx, model.mu_, model.cov_, s, model.weights,
                        model.meta, model.vrms_, model.vgain_)


def test_guard_brings_a_stream_whose_extrapolation_misleads_back_to_hold(small):
    """A constructed stream: a validation walk (walking_20) whose left leg stands still with a 3 deg,
    6 Hz tremor (no training take moves so: the onset velocity says nothing of where the leg goes),
    the leg dropping out for 0.25 s at random onsets every 0.5-1 s.  Without the guard the fill is
    worse than hold there (1.37x from the 4th gap); with it the fill is back near hold within four
    gaps (the take has seven)."""
    model, _ = small
    assert model.settings.guard_s > 0  # shipped on
    truth = splits.load_take("walking_20").frames.copy()
    T = truth.shape[0]
    cols = np.array([c.split(".")[0] in ("lfemur", "ltibia", "lfoot", "ltoes") for c in model.channels])
    truth[:, cols] = truth[0, cols] + 3.0 * np.sin(2 * np.pi * 6.0 * np.arange(T) / 120.0)[:, None]
    obs = np.ones(truth.shape, bool)
    starts = [s for s in np.cumsum(np.random.default_rng(0).integers(60, 120, 40)) + 30 if s < T - 40]
    for s in starts:
        obs[s:s + 30, cols] = False
    given = np.where(obs, truth, np.nan)
    held = np.where(obs, truth, np.nan)
    for t in range(1, T):
        held[t] = np.where(obs[t], truth[t], held[t - 1])
    fills = {"off": _with(model, guard_s=0.0).fill_offline(given, obs)[0], "on": model.fill_offline(given, obs)[0], "hold": held}

    def rms(name, first_gap):
        late = np.zeros(truth.shape, bool)
        late[starts[first_gap]:] = ~obs[starts[first_gap]:]
        return float(np.sqrt(np.mean(wrap(fills[name] - truth)[late] ** 2)))

    r = {n: rms(n, 3) for n in fills}
    assert r["off"] > 1.15 * r["hold"], r  # the construct does mislead the unguarded fill
    # from the 4th gap on the guard has removed >= 75% of the unguarded fill's excess over hold ...
    assert r["on"] - r["hold"] <= 0.25 * (r["off"] - r["hold"]), r
    # ... and from the 5th it is within 5% of hold (measured: 3.3%; 3 deg of tremor is all hold misses)
    assert rms("on", 4) <= 1.05 * rms("hold", 4), (rms("on", 4), rms("hold", 4))


def test_guard_off_is_the_fill_of_before_and_old_model_files_load_without_it(small, tmp_path):
    """guard_s = 0 (a model file saved before the guard existed has no guard_* settings): the
    fill is exactly the unguarded one; the shipped guard changes fills on real gaps."""
    model, _ = small
    off = _with(model, guard_s=0.0)
    p = tmp_path / "old.npz"
    off.save(str(p))
    meta, arrays = modelfile.load_arrays(str(p))
    for k in ("guard_s", "guard_n0", "guard_max"):
        meta["settings"].pop(k)
    old = type(model).load(str(p), meta, arrays)
    assert not old.guard_on
    truth = splits.load_take("walking_27").frames
    obs, _ = occlusion("walking_27", truth.shape[0], model.channels, 120.0, seed=1)
    given = np.where(obs, truth, np.nan)
    f_off, _ = off.fill_offline(given, obs)
    f_on, _ = model.fill_offline(given, obs)
    assert not np.allclose(f_on[~obs], f_off[~obs])
    np.testing.assert_array_equal(old.fill_offline(given, obs)[0], f_off)


def test_a_group_not_yet_checked_is_gated_by_how_the_regression_predicts_the_rest_of_the_stream(small):
    """49_19 (VALIDATION, a motion unlike the training takes') under the gaps protocol's bursts of seed 110:
    the right arm drops out at frame 36 for 1.4 s, before its own shadow check has run (and it cannot run
    while the arm is missing).  Gated by the prior rho = 1 alone (gate_n0 0, the fill of before) the
    regression gets 94% of its weight and the fill is far worse than hold; with the shipped gate_n0 the
    other groups' checks, whose regression is off by 100x their own change, gate the arm too, and the
    fill is hold's or better."""
    from mocap import protocols

    model, _ = small
    assert model.settings.gate_n0 > 0  # shipped on
    case = next(c for c in protocols.Gaps(seed=110, split="validation").cases() if c.test == "49_19")
    truth, obs = case.truth, case.observed
    arm = np.array([c.split(".")[0] in ("rhumerus", "rradius", "rwrist", "rhand", "rthumb") for c in model.channels])
    assert (~obs[36:200, arm]).all() and obs[:36].all()  # the construct: the arm out from frame 36
    given = np.where(obs, truth, np.nan)
    held = np.where(obs, truth, np.nan)
    for t in range(1, len(truth)):
        held[t] = np.where(obs[t], truth[t], held[t - 1])
    old = _with(model, gate_n0=0.0)

    ang = np.array([is_angle(c) for c in model.channels])

    def rms(f):
        return float(np.sqrt(np.mean(wrap(f - truth)[~obs & ang] ** 2)))

    r_old, r_new, r_hold = rms(old.fill_offline(given, obs)[0]), rms(model.fill_offline(given, obs)[0]), rms(held)
    assert r_old > 1.3 * r_hold, (r_old, r_hold)  # the construct misleads the prior-gated regression
    assert r_new <= r_hold, (r_new, r_hold)
    # the mechanism: in the gap the arm group's gate, with no check of its own, is the stream's
    st = model.stream()
    for t in range(60):
        st.step_numpy(given[t].copy(), obs[t].copy())
    g = np.unique(model.group[arm & model._is_reg])
    assert (st.NE[g] == 0).all() and (st.NE > 0).any()
    assert (st.gate(g) < 0.05).all(), st.gate(g)
    old_st = old.stream()
    for t in range(60):
        old_st.step_numpy(given[t].copy(), obs[t].copy())
    assert (old_st.gate(g) > 0.9).all(), old_st.gate(g)


def test_model_files_without_gate_n0_load_with_the_prior_gate(small, tmp_path):
    """A model file saved before gate_n0 existed loads with 0: the fill of before, bit for bit."""
    model, _ = small
    off = _with(model, gate_n0=0.0)
    p = tmp_path / "old.npz"
    off.save(str(p))
    meta, arrays = modelfile.load_arrays(str(p))
    meta["settings"].pop("gate_n0")
    old = type(model).load(str(p), meta, arrays)
    assert old.settings.gate_n0 == 0.0
    truth = splits.load_take("basketball_4").frames[:600]
    obs, _ = occlusion("basketball_4", truth.shape[0], model.channels, 120.0, seed=3)
    given = np.where(obs, truth, np.nan)
    np.testing.assert_array_equal(old.fill_offline(given, obs)[0], off.fill_offline(given, obs)[0])


def _gaps_figures(model, seeds):
    """lacuna eval's gaps protocol on the TEST takes: {activity: {metric: (default, hold)}}."""
    from mocap import metrics
    from mocap.protocols import GAP_GROUPS, Gaps

    vals: dict = {}
    hold = HoldModel.fit([splits.load_take(splits.TRAIN[0]).frames], model.channels)
    for seed in seeds:
        for case in Gaps(seed, "test").cases():
            given = np.where(case.observed, case.truth, np.nan)
            f, s = model.fill_offline(given, case.observed)
            h, _ = hold.fill_offline(given, case.observed)
            a = splits.ACTIVITY[case.test]
            groups = case.info.get("groups", GAP_GROUPS)
            vals.setdefault(a, ([], []))
            vals[a][0].append(metrics.values(case, f, s, groups))
            vals[a][1].append(metrics.values(case, h, None, groups))
    out = {}
    for a, (vd, vh) in vals.items():
        d = {m: (v, n) for m, v, n in metrics.summarise(metrics.Values.concat(vd), by_group_bins=False)}
        h = {m: v for m, v, _ in metrics.summarise(metrics.Values.concat(vh), by_group_bins=False)}
        out[a] = {m: (v, h.get(m), n) for m, (v, n) in d.items()}
    return out


@pytest.fixture(scope="module")
def test_figures(small):
    return _gaps_figures(small[0], (0, 1))


@pytest.mark.parametrize("activity", ["walk", "turn", "nonloco",
                                      pytest.param("run", marks=pytest.mark.xfail(strict=True, reason=(
                                          "issue 17, not met: one 1.4 s take (35_25), gaps 1-2 s and 0.5-1 s after "
                                          "onset (right arm) above hold; too short for the guard to learn")))])
def test_never_worse_than_hold_at_any_gap_length_on_test_takes(test_figures, activity):
    """The gaps protocol on the 12 TEST takes (seeds 0-1): at every gap length with at least 500
    erased values, default's RMS <= 1.02 x hold's (2%: between seeds 0-1 and 0-4 these cells move
    by up to ~2%, bench/notebook/guard.md); and over all gaps below hold."""
    fig = test_figures[activity]
    checked = 0
    for m, (v, h, n) in fig.items():
        if m.startswith("rms_deg[len") and v is not None and h is not None and n >= 500:
            assert v <= 1.02 * h, (activity, m, v, h)
            checked += 1
    assert checked >= 3
    assert fig["rms_deg"][0] < fig["rms_deg"][1]
    assert fig["rms_deg[first 0.1s]"][0] <= fig["hold_rms_deg[first 0.1s]"][0]


@pytest.mark.parametrize("activity", ["walk", "turn", "run", "nonloco"])
def test_two_std_band_holds_90_to_98_percent_on_test_takes(test_figures, activity):
    share = test_figures[activity]["within_2std"][0]
    assert 0.90 <= share <= 0.98, (activity, share)
