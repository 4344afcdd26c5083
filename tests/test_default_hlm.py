"""``default-hlm`` (blend/withhlm.py): default and the HLM side by side, on real takes.

The experts are trained small (a few TRAIN takes, the HLM with one restart and few EM steps) so the
file stays within the suite's budget; the stacking weights are the shipped ones (fitted on
VALIDATION by bench/default_hlm_tune.py).  Scored on TEST takes.
"""
from __future__ import annotations

import numpy as np
import pytest
from default_small import train_small

from blend.withhlm import ROOT_POS, WithHLMModel, shipped
from lacuna import jit, modelfile
from lacuna.cli import main as cli_main
from lacuna.filler import Fill, FillerState, Model, check_frame
from mocap import protocols, splits
from mocap.representation import is_angle
from mocap.rootrot import wrap180 as wrap

pytestmark = pytest.mark.realdata



@pytest.fixture(scope="module")
def model(data):
    return train_small()


def _pan2009(truth: np.ndarray, channels: list[str]) -> np.ndarray:
    legs = np.array([c.split(".")[0] in ("lfemur", "ltibia", "lfoot", "ltoes", "rfemur", "rtibia", "rfoot", "rtoes")
                     for c in channels])
    obs = np.ones(truth.shape, bool)
    obs[truth.shape[0] // 2:, ~legs] = False
    return obs


def _mse(truth, fill, obs, channels) -> float:
    ang = np.array([is_angle(c) for c in channels])
    e = wrap(fill - truth)[~obs & ang[None]]
    return float(np.mean(e ** 2))


def test_beats_default_on_a_test_walk_with_pan2009s_pattern(model):
    """TEST walk 35_30 (a subject-35 walk nobody trains or tunes on), root and upper body erased from
    half way: the blend's erased angles beat ``default``'s own, and the root position is default's."""
    truth = splits.load_take("35_30").frames
    ch = model.channels
    obs = _pan2009(truth, ch)
    given = np.where(obs, truth, np.nan)
    fill, std = model.fill_offline(given, obs)
    dfill, _ = model.default.fill_offline(given, obs)
    hfill, _ = model.hlm.fill_offline(given, obs)
    assert _mse(truth, fill, obs, ch) < 0.8 * _mse(truth, dfill, obs, ch)
    np.testing.assert_array_equal(fill[obs], truth[obs])        # observed values come back exactly
    assert (std[~obs] > 0).all() and (std[obs] == 0).all()
    pos = model.group == ROOT_POS
    np.testing.assert_allclose(fill[:, pos], dfill[:, pos])     # root translation: never the HLM's
    assert not np.allclose(fill[:, pos], hfill[:, pos])


def test_no_worse_than_default_on_a_test_take_that_is_not_locomotion(model):
    """TEST take basketball_signal_5 (referee signals), the gaps protocol's bursts: the shadow check
    sees that the HLM does not predict this body (q > 1) and the blend stays within 1% of
    ``default`` (q > 1.1 yields entirely, and until the first window is scored the HLM has no share;
    the old policy's prior q = 1 needed 3% here for the first second)."""
    c = [c for c in protocols.Gaps(seed=0, split="test").cases() if c.test == "basketball_signal_5"][0]
    T = 900
    truth, obs = c.truth[:T], c.observed[:T]
    given = np.where(obs, truth, np.nan)
    st = model.stream()
    fill = np.empty(truth.shape)
    for t in range(T):
        fill[t] = st.step(given[t], obs[t]).frame
    dfill, _ = model.default.fill_offline(given, obs)
    assert st.m is model and np.exp(st.logq) > 1.0
    assert _mse(truth, fill, obs, c.channels) <= 1.01 * _mse(truth, dfill, obs, c.channels)


def test_model_file_round_trip_and_batch_equals_streams(model, tmp_path):
    truth = splits.load_take("walking_27").frames[:400]
    obs = _pan2009(truth, model.channels)
    obs[:100, :] = True
    p = str(tmp_path / "dh.npz")
    model.save(p)
    back = modelfile.load_model(p)
    assert isinstance(back, WithHLMModel) and back.tau == model.tau
    np.testing.assert_array_equal(back.W, model.W)
    a, sa = model.fill_offline(np.where(obs, truth, np.nan), obs)
    b, sb = back.fill_offline(np.where(obs, truth, np.nan), obs)
    np.testing.assert_allclose(a, b, atol=1e-9)
    np.testing.assert_allclose(sa, sb, atol=1e-9)
    # two streams through step_batch (the daemon's path) give what each stream gives alone
    obs2 = obs.copy()
    obs2[150:250, :20] = False
    states = [back.stream(), back.stream()]
    F = np.stack([truth, truth], 1)
    O = np.stack([obs, obs2], 1)
    out = np.stack([[f.frame for f in back.step_batch(states, F[t], O[t])] for t in range(len(truth))])
    np.testing.assert_allclose(out[:, 0], b, atol=1e-9)
    c, _ = back.fill_offline(np.where(obs2, truth, np.nan), obs2)
    np.testing.assert_allclose(out[:, 1], c, atol=1e-9)


def test_truncated_model_file_is_a_clear_error(model, tmp_path, capsys):
    p = tmp_path / "dh.npz"
    model.save(str(p))
    cut = tmp_path / "cut.npz"
    cut.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    with pytest.raises(modelfile.ModelFileError, match="truncated or corrupt"):
        modelfile.load_model(str(cut))
    rc = cli_main(["eval", "--protocol", "pan2009", "--split", "test", "--method", "default-hlm", "--model", str(cut), "-q"])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("lacuna: error:") and "cut.npz" in err and len(err.strip().splitlines()) == 1
    # a file whose experts' metadata is missing names what is wrong
    meta, arrays = modelfile.load_arrays(str(p))
    del meta["experts"]
    bad = tmp_path / "bad.npz"
    modelfile.save_arrays(str(bad), meta, arrays)
    with pytest.raises(modelfile.ModelFileError, match="two experts"):
        modelfile.load_model(str(bad))


def test_train_without_a_locomotion_file_is_a_clear_error(data, tmp_path, capsys):
    files = [str(splits.take_path(t)) for t in ("basketball_1", "soccer_1")]
    rc = cli_main(["train", "default-hlm", *files, "-o", str(tmp_path / "dh.npz"), "-q"])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("lacuna: error:") and "locomotion" in err
    assert not (tmp_path / "dh.npz").exists()


@pytest.mark.skipif(not jit.enabled(), reason="numba cannot run in this process: only the numpy mixing serves")
def test_compiled_mixing_equals_the_numpy_mixing(model):
    """TEST take 35_30 with the gaps protocol's bursts (seed 0): one stream mixed by the compiled
    kernel (blend/withhlm_fast.py), one by the numpy reference, frame by frame; fills and stds agree
    to 1e-9 through real gaps and through shadow windows (their twin and q included)."""
    c = [c for c in protocols.Gaps(seed=0, split="test").cases() if c.test == "35_30"][0]
    T = len(c.truth)
    a, b = model.stream(), model.stream()
    windows = gaps = 0
    try:
        for t in range(T):
            model.compiled = True
            fa = a.step(c.truth[t], c.observed[t])
            model.compiled = False
            fb = b.step(c.truth[t], c.observed[t])
            np.testing.assert_allclose(fa.frame, fb.frame, rtol=0, atol=1e-9)
            np.testing.assert_allclose(fa.std, fb.std, rtol=0, atol=1e-9)
            windows += a.sh >= 0
            gaps += fa.filled.any()
    finally:
        model.compiled = jit.enabled()
    assert windows > 60 and gaps > 60            # both paths were exercised
    assert a.logq != 0.0 and abs(a.logq - b.logq) < 1e-9 and (a.k == b.k).all()


class _Scripted(Model):
    """A constructed second expert for one take: the truth plus a scripted error on every value it is
    not shown (``err(t)``, (C,) degrees).  The blend is the real one; only the HLM's slot is scripted,
    so the online check's policy is judged on an expert whose quality is known from the first frame."""

    method = "scripted"

    def __init__(self, truth: np.ndarray, channels: list[str], err):
        self.truth, self.channels, self.err = truth, list(channels), err

    def stream(self) -> FillerState:
        return _ScriptedState(self)


class _ScriptedState(FillerState):
    def __init__(self, m: _Scripted):
        self.m, self.t = m, 0

    def step(self, frame, observed=None) -> Fill:
        f, obs = check_frame(frame, observed, self.m.n_channels)
        out = np.where(obs, f, self.m.truth[self.t] + self.m.err(self.t))
        self.t += 1
        return Fill(out, np.where(obs, 0.0, 5.0), ~obs, {})


def _mixed_vs_blend(model, err, take="walking_24", T=1200, closes=None):
    """One stream of ``default`` whose HLM is scripted, on TEST take ``take`` (a turning walk of
    another performer): a limb group erased for 0.75 s every 1.6 s, the first from frame 5 (before
    any window of the check can close).  Per gap (in order of onset) the squared errors of the mix and
    of the blend alone over the erased angles, and the stream's state at the end."""
    truth = splits.load_take(take).frames[:T]
    obs = np.ones(truth.shape, bool)
    for i, t0 in enumerate(range(5, T - 90, 190)):
        obs[t0:t0 + 90, model.group == (3, 4, 5, 2)[i % 4]] = False     # left arm, right arm, left leg, head
    W, S, chosen = shipped()
    mixed = WithHLMModel(model.default, _Scripted(truth, model.channels, err), W, S, tau=float(chosen.get("tau", 15.0)))
    st, ds = mixed.stream(), model.default.stream()
    ang = np.array([is_angle(ch) for ch in model.channels])
    onset = np.full(len(ang), -1)       # each channel's gap onset frame, -1 while observed
    per: dict[int, list[float]] = {}
    n_win = 0
    for t in range(T):
        a, b = st.step(truth[t], obs[t]).frame, ds.step(truth[t], obs[t]).frame
        if closes is not None and st.n_win > n_win:
            n_win = st.n_win
            closes.append((t, float(np.exp(st.logq))))
        miss = ~obs[t] & ang
        onset = np.where(obs[t], -1, np.where(onset < 0, t, onset))
        for j in np.flatnonzero(miss):
            e = per.setdefault(int(onset[j]), [0.0, 0.0])
            e[0] += float(wrap(a[j] - truth[t, j]) ** 2)
            e[1] += float(wrap(b[j] - truth[t, j]) ** 2)
    return [per[k] for k in sorted(per)], st


def test_an_hlm_wrong_from_the_first_frame_never_gets_a_share(model):
    """The second expert is 20-30 deg off on everything it fills, from the first frame (a motion the
    HLM does not know).  Until the online check has scored it the HLM's share is 0 (the pessimistic
    bound starts at "no evidence"), and once scored its bound on q is far above 1.1: every gap of the
    stream, the first one included, is filled as the blend alone fills it (within 1%).  The old policy
    (a prior window at q = 1) gave the HLM the validation-fitted share of the q bin 0.7-1.1 on every gap
    before the first window closed."""
    rng = np.random.default_rng(0)
    off = rng.uniform(20, 30, len(model.channels)) * rng.choice([-1, 1], len(model.channels))
    gaps, st = _mixed_vs_blend(model, lambda t: off * np.sin(2 * np.pi * t / 90.0 + 1.0))
    assert len(gaps) == 6
    for mix, blend in gaps:
        assert mix <= 1.01 * blend + 1e-9
    assert st.lr_n > 0 and np.exp(st.logq) > 1.1      # it was scored, and judged worse than the blend


def test_an_hlm_that_is_right_gets_its_share_once_scored(model):
    """The second expert fills every value it is not shown with the truth: once the check has scored
    a window the mix leans on it and the gaps after that are filled far better than by the blend."""
    gaps, st = _mixed_vs_blend(model, lambda t: 0.0)
    assert np.exp(st.logq) < 0.4
    later = np.array(gaps[len(gaps) // 4:])
    assert later[:, 0].sum() < 0.5 * later[:, 1].sum()
    first = np.array(gaps)
    assert first[:, 0].sum() <= first[:, 1].sum()


def test_an_hlm_right_for_seconds_then_wrong_loses_its_share_at_the_first_window_that_sees_it(model):
    """The second expert is the truth for the stream's first 600 frames (its windows score it far better
    than the blend), then 20-30 deg off (a performer who stops walking).  The first window that sees it
    wrong revokes its share (SHADOW_REVOKE): every gap opening after that window closed is filled as
    the blend fills it (within 1%), and the stream over all its gaps is no worse than the blend's.  The
    decayed bound alone (SHADOW_REVOKE 0) keeps q+ under 0.4 after that window: the good windows
    outweigh the bad one, and the HLM keeps its share for seconds."""
    rng = np.random.default_rng(1)
    off = rng.uniform(20, 30, len(model.channels)) * rng.choice([-1, 1], len(model.channels))
    closes: list[tuple[int, float]] = []
    T, turn = 1310, 600
    truth = splits.load_take("walking_24").frames[:T]
    gaps, st = _mixed_vs_blend(model, lambda t: 0.0 if t < turn else off * np.sin(2 * np.pi * t / 90.0 + 1.0),
                               T=T, closes=closes)
    assert truth.shape[0] == T
    seen = [t for t, _ in closes if t - 60 >= turn]       # windows wholly after the turn
    assert seen and dict(closes)[seen[0]] > 1.1           # the first one that saw it wrong: the HLM yields
    onsets = list(range(5, T - 90, 190))
    after = [g for t0, g in zip(onsets, gaps, strict=True) if t0 > seen[0]]
    assert len(after) >= 2
    for mix, blend in after:
        assert mix <= 1.01 * blend + 1e-9
    tot = np.array(gaps).sum(0)
    assert tot[0] <= tot[1]


def test_one_window_that_finds_the_hlm_somewhat_better_is_not_enough_evidence(model, tmp_path):
    """The bound's prior window sits at the share's cut (Q_PRIOR_AT = log 1.1, bench/notebook/loao-41.md):
    one shadow window where the HLM's error is 25% under the blend's (the chance win that handed it
    held-out jumps and subject 49) leaves the bound above the cut, one where it is half the blend's
    gives it a share at once, and a second 25%-better window does too (the prior's pull fades).  The
    model keeps its prior (its W/S were fitted under it); a file written before it fills with 0, as then."""
    import math

    from blend import withhlm

    cut = float(withhlm.Q_EDGES[-1])
    pa = withhlm.Q_PRIOR_AT
    assert pa == pytest.approx(math.log(1.1)) and cut == pytest.approx(math.log(1.1))
    one = withhlm._bound(0.0, 0.0, 0.0, 0.75, 1.0, pa)
    assert one[3] > cut                                            # no share on one 0.75 window
    assert withhlm._bound(0.0, 0.0, 0.0, 0.5, 1.0, pa)[3] < cut    # a clear win: a share at once
    assert withhlm._bound(*one[:3], 0.75, 1.0, pa)[3] < cut        # the same evidence twice: a share
    assert withhlm._bound(0.0, 0.0, 0.0, 0.75, 1.0, 0.0)[3] < cut  # the old prior: one 0.75 window was enough

    assert model.prior_at == pa
    path = tmp_path / "d.npz"
    model.save(str(path))
    assert modelfile.load_model(str(path)).prior_at == pa
    meta, arrays = modelfile.load_arrays(str(path))
    del meta["prior_at"]
    old = tmp_path / "old.npz"
    modelfile.save_arrays(str(old), meta, arrays)
    assert modelfile.load_model(str(old)).prior_at == 0.0
    meta["prior_at"] = "log 1.1"
    modelfile.save_arrays(str(old), meta, arrays)
    with pytest.raises(modelfile.ModelFileError, match="prior_at"):
        modelfile.load_model(str(old))


def test_the_shipped_weights_were_fitted_under_the_check_the_code_runs():
    """blend/withhlm.json's W and S are only right for the policy they were fitted under: the policy
    it records is the module's."""
    from blend import withhlm

    pol = shipped()[2]["policy"]
    assert (pol["Q_Z"], pol["SHADOW_SKIP"], pol["SHADOW_MAX_MISS"], pol["SHADOW_WARM"], pol["SHADOW_EAGER"],
            pol["Q_PRIOR_N"], pol.get("Q_PRIOR_AT", 0.0), pol["SHADOW_REVOKE"]) == \
        (withhlm.Q_Z, withhlm.SHADOW_SKIP, withhlm.SHADOW_MAX_MISS, withhlm.SHADOW_WARM, withhlm.SHADOW_EAGER,
         withhlm.Q_PRIOR_N, withhlm.Q_PRIOR_AT, withhlm.SHADOW_REVOKE)


def _long_erasure(model, trust, q, legs_out=False, compiled=True, take="35_30"):
    """pan2009's pattern on TEST take ``take`` (every channel but the legs erased from half way), the
    HLM's slot scripted to the truth, the stream's bound on q held at ``q`` from the erasure on (the
    check cannot run then: > SHADOW_MAX_MISS missing); with ``legs_out`` one leg channel is missing too.
    Returns the fills, the erasure's first frame and the erased upper-body angles' mask."""
    import math

    truth = splits.load_take(take).frames
    obs = _pan2009(truth, model.channels)
    t0 = truth.shape[0] // 2
    legs = np.isin(model.group, (5, 6))
    if legs_out:
        obs[t0:, np.flatnonzero(legs)[0]] = False
    W, S, chosen = shipped()
    meta = {"long_trust": list(trust)} if trust else {}
    m = WithHLMModel(model.default, _Scripted(truth, model.channels, lambda t: 0.0), W, S, meta,
                     tau=float(chosen.get("tau", 15.0)))
    m.compiled = compiled and jit.enabled()
    st = m.stream()
    out = np.empty_like(truth)
    for t in range(len(truth)):
        if t >= t0:
            st._lq = math.log(q)
        out[t] = st.step(truth[t], obs[t]).frame
    ang = np.array([is_angle(c) for c in model.channels])
    body = ~legs & ang & (model.group != ROOT_POS)
    return out, truth, t0, body


def test_long_erasure_trust_takes_the_hlms_share_only_after_k_frames_with_the_legs_seen(model):
    """q+ 1.3 (the last bin: the HLM yields without the trust): with the trust (120, 1.5) the fill is
    main's for the erasure's first 120 frames, then leans on the (here perfect) HLM: the upper body's
    error from frame 120 on falls below half of main's.  With q+ above QMAX, or a leg channel missing,
    it is main's throughout; compiled and numpy mixing agree."""
    off, truth, t0, body = _long_erasure(model, None, 1.3)
    on, _, _, _ = _long_erasure(model, (120, 1.5), 1.3)
    np.testing.assert_allclose(on[: t0 + 119], off[: t0 + 119], rtol=0, atol=1e-12)
    e_on = np.mean(wrap(on[t0 + 119:, body] - truth[t0 + 119:, body]) ** 2)
    e_off = np.mean(wrap(off[t0 + 119:, body] - truth[t0 + 119:, body]) ** 2)
    assert e_on < 0.5 * e_off
    high, _, _, _ = _long_erasure(model, (120, 1.5), 2.0)
    np.testing.assert_allclose(high, off, rtol=0, atol=1e-12)
    leg_off, _, _, _ = _long_erasure(model, None, 1.3, legs_out=True)
    leg_on, _, _, _ = _long_erasure(model, (120, 1.5), 1.3, legs_out=True)
    np.testing.assert_allclose(leg_on, leg_off, rtol=0, atol=1e-12)
    numpy_on, _, _, _ = _long_erasure(model, (120, 1.5), 1.3, compiled=False)
    np.testing.assert_allclose(numpy_on, on, rtol=0, atol=1e-9)


def test_long_erasure_trust_is_off_by_default_and_kept_by_the_model_file(model, tmp_path):
    """A trained model has the trust off (bench/notebook/pan-11.md: it opens on non-locomotion); one
    set on keeps it through its file, and a file without the key loads with it off."""
    from blend import withhlm

    assert model.long_trust == withhlm.LONG_TRUST_OFF == (0, 0.0)
    p = tmp_path / "m.npz"
    model.set_long_trust(120, 1.5)
    try:
        model.save(str(p))
        assert modelfile.load_model(str(p)).long_trust == (120, 1.5)
    finally:
        model.set_long_trust(*withhlm.LONG_TRUST_OFF)
    model.save(str(p))
    assert modelfile.load_model(str(p)).long_trust == (0, 0.0)
