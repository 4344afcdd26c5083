"""The online HLM filter behind the Filler seam: equals the offline forward pass, batches exactly,
is causal, passes observed values through, predicts through dropped frames, and its fixed-lag
stream converges to the offline smoother."""
import numpy as np
import pytest

from hlm import offline, online
from hlm.methods import train_model
from hlm.synthetic import random_cycles, sample
from lacuna.filler import FillerError

C, M, F = 2, 40, 6
CH = [f"j{i}.tx" for i in range(F)]


@pytest.fixture(scope="module")
def world():
    rng = np.random.default_rng(11)
    Z = random_cycles(C, M, F, rng)
    lam = np.full((C, F), 4.0)
    seqs, truth = sample(Z, lam, [100] * 8, rng, labels=np.array([0, 1] * 4))
    test, ttruth = sample(Z, lam, [80, 80], rng, labels=np.array([0, 1]))
    model = train_model(seqs, CH, styles=C, cycle_frames=M // 2, restarts=2, n_iter=8, root_mode="raw",
                        normalize=True, kappa=0.0)
    return model, test, ttruth, truth


def _mask(rng, T, p=0.3):
    obs = rng.random((T, F)) > p
    obs[T // 2 :, :3] = False     # a long gap on half the channels
    return obs


def test_online_posterior_equals_offline_forward_pass(world, rng):
    """The paper's filter (no stream-cycle adaptation, no change of style) is the offline forward
    pass; the extensions are checked against a textbook recursion below."""
    model, test, _, _ = world
    for _ in range(2):
        m = model.with_options(kappa=0.0, style_switch=0.0)
        x = test[0]
        obs = _mask(rng, x.shape[0])
        st = m.stream()
        posts = []
        for t in range(x.shape[0]):
            st.step(np.where(obs[t], x[t], np.nan), obs[t])
            posts.append(st.core_state["post"][0].copy())
        z = m.representation.transform(x)
        zobs = m.representation.feature_observed(obs)
        ref = offline.forward_filter(m.tables, np.where(zobs, z, np.nan), zobs)
        np.testing.assert_allclose(np.array(posts), ref, atol=1e-10)


@pytest.mark.parametrize("layout", ["contiguous", "interleaved"])
def test_batched_step_equals_single_streams(world, rng, layout):
    """Batched == one stream at a time, whether the batch's pool slots are contiguous (stepped
    through views of the pool) or interleaved with other streams' and given out of order (rows
    gathered; the stream-cycle statistics indexed in the pool by row)."""
    model, test, _, _ = world
    m = model.with_options(kappa=0.5, kappa_global=1.0)
    xs = [test[0], test[1], test[0][::-1].copy()]
    obs = [_mask(rng, x.shape[0]) for x in xs]
    obs[2][10:15] = False          # frames that never arrived, in one stream only
    if layout == "contiguous":
        singles = [m.stream() for _ in xs]
        batch = [m.stream() for _ in xs]
        order = np.arange(3)
    else:
        pairs = [(m.stream(), m.stream()) for _ in xs]
        singles, batch = [p[0] for p in pairs], [p[1] for p in pairs]
        order = np.array([2, 0, 1])
        assert [b.slot for b in batch] == [1, 3, 5]
    for t in range(60):
        fr = np.stack([np.where(o[t], x[t], np.nan) for x, o in zip(xs, obs)])
        ob = np.stack([o[t] for o in obs])
        got = m.step_batch([batch[i] for i in order], fr[order], ob[order])
        got = [got[int(np.flatnonzero(order == i)[0])] for i in range(3)]
        for i, s in enumerate(singles):
            want = s.step(fr[i], ob[i])
            np.testing.assert_allclose(got[i].frame, want.frame, rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(got[i].std, want.std, rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(got[i].extras["style"], want.extras["style"], atol=1e-12)
            assert got[i].extras["phase"] == pytest.approx(want.extras["phase"], abs=1e-12)


def test_causal_changing_the_future_never_changes_the_past(world, rng):
    model, test, _, _ = world
    x = test[0]
    obs = _mask(rng, x.shape[0])
    a, b = model.stream(), model.stream()
    y = x.copy()
    y[41:] += rng.normal(0, 3.0, y[41:].shape)
    for t in range(41):
        fa = a.step(np.where(obs[t], x[t], np.nan), obs[t])
        fb = b.step(np.where(obs[t], y[t], np.nan), obs[t])
        np.testing.assert_array_equal(fa.frame, fb.frame)
        np.testing.assert_array_equal(fa.std, fb.std)


def test_nothing_missing_returns_the_frame_unchanged(world):
    model, test, _, _ = world
    st = model.stream()
    for t in range(30):
        f = st.step(test[0][t], np.ones(F, bool))
        np.testing.assert_array_equal(f.frame, test[0][t])
        assert not f.std.any() and not f.filled.any()


def test_dropped_frame_is_a_prediction_step(world):
    model, test, _, _ = world
    st = model.stream()
    for t in range(20):
        st.step(test[0][t], np.ones(F, bool))
    before = st.core_state["post"].copy()
    f = st.step(None)
    want = online.switch_styles(online.predict(before, st.core_state["d"]), model.tables.style_switch)
    if model.tables.style_switch > 0:
        want[want < online.PRUNE * want.max()] = 0.0   # negligible states are dropped with the switch
    np.testing.assert_allclose(st.core_state["post"], want / want.sum(), atol=1e-14)
    assert f.filled.all() and np.isfinite(f.frame).all() and (f.std > 0).all()


def test_style_posterior_phase_and_calibrated_std(world):
    model, test, ttruth, truth = world
    m = model.with_options(kappa=0.0)
    # map learned styles to true ones through the training sequences
    assign = np.array(m.meta["training"]["psi"]).argmax(1)
    zs = []
    for k in range(2):
        x = test[k]
        obs = np.ones(x.shape, bool)
        obs[20:, :3] = False
        st = m.stream()
        for t in range(x.shape[0]):
            f = st.step(np.where(obs[t], x[t], np.nan), obs[t])
            if t >= 20:
                zs.append((f.frame[:3] - x[t, :3]) / f.std[:3])
        style = np.array(f.extras["style"])
        assert style.sum() == pytest.approx(1.0)
        learned = int(style.argmax())
        assert np.bincount(truth.labels[assign == learned]).argmax() == ttruth.labels[k]
        assert 0.0 <= f.extras["phase"] < 1.0
    zs = np.concatenate(zs)
    assert 0.6 < zs.std() < 1.6     # the reported std is the size of the actual error


def test_fixed_lag_stream_converges_to_offline_smoother(world, rng):
    model, test, _, _ = world
    m = model.with_options(kappa=0.0, n_iter_d=0, style_switch=0.0)   # the offline smoother is the paper's
    x = test[1][:50]
    obs = _mask(rng, x.shape[0])
    want, want_sd = m.fill_smoothed(np.where(obs, x, np.nan), obs)
    got, got_sd = m.fill_lagged(np.where(obs, x, np.nan), obs, lag=x.shape[0])
    np.testing.assert_allclose(got, want, atol=1e-8)
    np.testing.assert_allclose(got_sd, want_sd, atol=1e-8)
    # lag 0 is the causal filter itself
    got0, _ = m.fill_lagged(np.where(obs, x, np.nan), obs, lag=0)
    causal, _ = m.fill_offline(np.where(obs, x, np.nan), obs)
    np.testing.assert_allclose(got0, causal, atol=1e-10)
    # a lag stream emits nothing for its first L frames, then one fill per frame
    st = m.lag_stream(5)
    outs = [st.step(np.where(obs[t], x[t], np.nan), obs[t]) for t in range(10)]
    assert outs[:5] == [None] * 5 and all(o is not None for o in outs[5:])
    assert len(st.flush()) == 5


def test_transition_adaptation_follows_a_faster_performer(world):
    model, _, _, _ = world
    rng = np.random.default_rng(3)
    p = model.params
    Zf = p.mu[:, :, :] * model.representation.std + np.array(model.representation.mean)  # back to raw units
    fast, _ = sample(Zf, np.full((C, F), 4.0), [300], rng, d_alpha=(0.2, 0.2, 20.0), labels=np.array([0]))
    m = model.with_options(adapt_rate=0.01, prior_strength=20.0)
    st = m.stream()
    for x in fast[0]:
        st.step(x, np.ones(F, bool))
    d = st.core_state["d"][0]
    d0 = m.tables.d_pop
    assert d @ np.arange(1, 4) > d0 @ np.arange(1, 4) + 0.3


def test_bad_frames_get_clear_errors(world):
    model, _, _, _ = world
    st = model.stream()
    with pytest.raises(FillerError, match="6 channels"):
        st.step(np.zeros(5))
    with pytest.raises(FillerError, match="finite"):
        st.step(np.full(F, np.nan), np.ones(F, bool))
    with pytest.raises(FillerError, match="shape"):
        model.fill_smoothed(np.zeros((10, 4)), np.ones((10, 4), bool))


def test_stream_cycle_adaptation_learns_a_performers_offset(world):
    """A performer who holds channel 0 three units higher than the training population: once a
    cycle has been seen, the adapted filler fills it with the offset; the paper's filler cannot."""
    model, test, _, _ = world
    x = test[0].copy()
    x[:, 0] += 3.0
    obs = np.ones(x.shape, bool)
    obs[45:, 0] = False
    errs = {}
    for kappa in (0.0, 3.0):
        m = model.with_options(kappa=kappa, kappa_global=kappa, width=3)
        filled, _ = m.fill_offline(np.where(obs, x, np.nan), obs)
        errs[kappa] = np.sqrt(np.mean((filled[45:, 0] - x[45:, 0]) ** 2))
    assert errs[0.0] > 2.5                 # the offset itself
    assert errs[3.0] < 0.5 * errs[0.0]


def _accumulate_per_stream(tab, D, W, P, z, zobs):
    """The stream-by-stream statistics update that ``online.accumulate`` vectorises (reference)."""
    o = zobs.astype(np.float64)
    for i in range(P.shape[0]):
        if not zobs[i].any():
            continue
        Pf = P[i].reshape(-1)
        rows = np.flatnonzero(Pf > online.LIVE_STATS * Pf.max())
        p, a = Pf[rows], tab.bin_a[rows]
        dev = o[i] * (np.where(zobs[i], z[i], 0.0) - tab.mu[rows])
        bins = np.concatenate([tab.bin0[rows], tab.bin1[rows]])
        wts = np.concatenate([p * (1.0 - a), p * a])[:, None]
        np.add.at(D[i], bins, wts * np.concatenate([dev, dev]))
        np.add.at(W[i], bins, wts * o[i])


def _fill_per_stream(tab, P, z, zobs, D, W):
    """The stream-by-stream fill that ``online.fill`` vectorises (reference)."""
    out, sd = z.copy(), np.zeros_like(z)
    for i in range(P.shape[0]):
        miss = ~zobs[i]
        if not miss.any():
            continue
        Pf = P[i].reshape(-1)
        rows = np.flatnonzero(Pf > online.LIVE * Pf.max())
        p = Pf[rows] / Pf[rows].sum()
        if D is None:
            mu = tab.mu[rows]
        else:
            mu = tab.mu[rows] + online.stream_offset(tab, rows, D[i], W[i])
        lam = tab.lam_rows[rows]
        val = (p @ (lam * mu)) / (p @ lam)
        mean, m2 = p @ mu, p @ (mu * mu + tab.var_q[rows])
        out[i, miss] = val[miss]
        sd[i, miss] = np.sqrt(np.maximum(m2 - mean * mean, 0.0) + (mean - val) ** 2)[miss]
    return out, sd


@pytest.mark.parametrize("kappa, kappa_global", [(0.0, 0.0), (0.5, 0.0), (0.5, 2.0)])
def test_vectorised_batch_step_equals_per_stream_loop(world, rng, kappa, kappa_global):
    model, test, _, _ = world
    m = model.with_options(kappa=kappa, kappa_global=kappa_global, width=2)
    tab = m.tables
    n = 7
    z_all = m.representation.transform(np.concatenate(test))
    st = m.core_init(n)
    D = W = None
    if kappa > 0:
        D, W = np.zeros_like(st["D"]), np.zeros_like(st["W"])
    for t in range(70):
        rows = (t + np.arange(n) * 11) % z_all.shape[0]
        zobs = rng.random((n, F)) > 0.4
        zobs[0] = False            # a frame that never arrived
        zobs[1] = True             # nothing missing
        zobs[2, :3] = False        # the long gap on half the features
        z = np.where(zobs, z_all[rows], np.nan)
        online.update(tab, st, z, zobs)
        online.accumulate(tab, st, z, zobs)
        if D is not None:
            _accumulate_per_stream(tab, D, W, st["post"], z, zobs)
            np.testing.assert_allclose(st["D"], D, rtol=0, atol=1e-9)
            np.testing.assert_allclose(st["W"], W, rtol=0, atol=1e-9)
        got = online.fill(tab, st["post"], z, zobs, *online.cycle_stats(st), **online.group_stats(st))
        want = _fill_per_stream(tab, st["post"], z, zobs, D, W)
        np.testing.assert_allclose(got[0], want[0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(got[1], want[1], rtol=0, atol=1e-9)
        assert np.array_equal(np.isnan(got[0]), np.isnan(want[0]))
    if D is not None:
        assert np.abs(st["D"]).max() > 0.0    # the statistics did move: the comparison is not of zeros


@pytest.mark.parametrize("kappa_global", [0.0, 2.0])
def test_lone_stream_paths_equal_the_per_stream_reference(world, rng, kappa_global):
    """A batch of one takes the direct paths of ``update``, ``accumulate`` and ``fill`` (fewer numpy
    calls; the offset from ``knot_offsets``); they must equal the reference loops above."""
    model, test, _, _ = world
    m = model.with_options(kappa=0.5, kappa_global=kappa_global, width=2)
    tab = m.tables
    z_all = m.representation.transform(test[0])
    st, ref = m.core_init(1), m.core_init(2)     # ref row 0 steps through the batched update
    D, W = np.zeros_like(st["D"]), np.zeros_like(st["W"])
    for t in range(70):
        zobs = rng.random((1, F)) > 0.4
        zobs[:, :3] = t < 30
        if t % 17 == 5:
            zobs[:] = False                       # a frame that never arrived
        z = np.where(zobs, z_all[t % z_all.shape[0]], np.nan)
        for k in ("D", "W", "G", "GW"):                      # the same statistics behind the emission
            ref[k][:] = st[k][0]
        ll = online.update(tab, st, z, zobs)
        ll2 = online.update(tab, ref, np.repeat(z, 2, 0), np.repeat(zobs, 2, 0))
        np.testing.assert_allclose(st["post"][0], ref["post"][0], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(np.isfinite(ll[0]), np.isfinite(ll2[0]))
        online.accumulate(tab, st, z, zobs)
        _accumulate_per_stream(tab, D, W, st["post"], z, zobs)
        np.testing.assert_allclose(st["D"], D, rtol=0, atol=1e-9)
        np.testing.assert_allclose(st["W"], W, rtol=0, atol=1e-9)
        got = online.fill(tab, st["post"], z, zobs, st["D"], st["W"], **online.group_stats(st))
        want = _fill_per_stream(tab, st["post"], z, zobs, D, W)
        np.testing.assert_allclose(got[0], want[0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(got[1], want[1], rtol=0, atol=1e-9)
    assert np.abs(D).max() > 0.0


@pytest.mark.parametrize("n", [1, 3])
def test_adapted_filter_equals_textbook_recursion_on_the_streams_own_cycle(world, rng, n):
    """With stream-cycle adaptation (kappa > 0) the emission is weighed on the stream's own cycle
    mu + delta (delta from the statistics of the frames before), and with style_switch > 0 the
    prediction moves mass h / (C - 1) to each other style at the same phase.  Written out the
    slow way, state by state, the recursion must equal the filter's (lone and batched paths)."""
    model, test, _, _ = world
    h = 0.01
    m = model.with_options(kappa=0.5, kappa_global=1.0, width=2, style_switch=h)
    tab = m.tables
    Cs, Ms = tab.shape
    z_all = m.representation.transform(np.concatenate(test))
    st = m.core_init(n)
    D, W = np.zeros_like(st["D"]), np.zeros_like(st["W"])
    post = None
    for t in range(60):
        zobs = rng.random((n, F)) > 0.4
        zobs[:, :3] = t < 25                     # half the features go missing for good
        rows_t = (t + np.arange(n) * 13) % z_all.shape[0]
        z = np.where(zobs, z_all[rows_t], np.nan)
        # reference: predict, change of style, emission on mu + delta, normalise
        if post is None:
            pr = np.exp(np.broadcast_to(tab.log_prior, (n, Cs, Ms))).copy()
        else:
            pr = online.predict(post, np.tile(tab.d_pop, (n, 1)))
            # only states above SWITCH_LIVE of their stream's largest mass change style
            src = pr * (pr > online.SWITCH_LIVE * pr.max(axis=(1, 2), keepdims=True))
            pr = pr - h * src + h / (Cs - 1) * (src.sum(1, keepdims=True) - src)
        want = np.zeros_like(pr)
        for i in range(n):
            allrows = np.arange(Cs * Ms)
            mu = tab.mu + online.stream_offset(tab, allrows, D[i], W[i])
            lam = tab.lam_rows
            o = zobs[i]
            ll = (0.5 * np.log(lam / (2 * np.pi)) - 0.5 * lam * ((np.where(o, z[i], 0.0) - mu) ** 2 + tab.var))[:, o].sum(1)
            with np.errstate(under="ignore"):
                w = pr[i].reshape(-1) * np.exp(ll - ll[pr[i].reshape(-1) > 0].max())
            w[w < online.PRUNE * w.max()] = 0.0          # with the switch, negligible states are dropped
            want[i] = (w / w.sum()).reshape(Cs, Ms)
        online.update(tab, st, z, zobs)
        np.testing.assert_allclose(st["post"], want, rtol=1e-9, atol=1e-12)
        online.accumulate(tab, st, z, zobs)
        _accumulate_per_stream(tab, D, W, st["post"], z, zobs)
        post = want
    assert np.abs(D).max() > 0.0


def test_a_change_of_style_mid_take_is_followed_only_with_style_switch(world, rng):
    """A performer walks, then runs (style 0, then style 1 of the generating process).  The paper's
    filter keeps one style per recording: once the other style's posterior has underflowed it can
    never come back, and the rest of the take is filled with the wrong style.  With style_switch
    the filter follows within a few frames, and the fills of the second part are better."""
    model, test, ttruth, _ = world
    x = np.concatenate([test[0], test[1]])
    obs = np.ones(x.shape, bool)
    obs[:, :3] = False                             # three channels missing throughout
    T0 = test[0].shape[0]
    out = {}
    for h in (0.0, 1e-3):
        st = model.with_options(style_switch=h).stream()
        fills = [st.step(np.where(obs[t], x[t], np.nan), obs[t]) for t in range(x.shape[0])]
        style = np.array([np.argmax(f.extras["style"]) for f in fills])
        err = np.sqrt(np.mean((np.array([f.frame for f in fills])[T0 + 10 :, :3] - x[T0 + 10 :, :3]) ** 2))
        out[h] = style, err
    s0, s1 = out[0.0][0], out[1e-3][0]
    first = s1[T0 - 10 : T0].tolist()
    assert len(set(first)) == 1 and (s0[T0 - 10 : T0] == first[0]).all()     # both agree on the walk
    assert (s0[T0:] == first[0]).all(), "the paper's filter should stay with the first style"
    assert (s1[T0 + 10 :] != first[0]).all(), "with style_switch the filter must follow the change"
    assert out[1e-3][1] < out[0.0][1]
