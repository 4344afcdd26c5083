"""The compiled single-stream steps (hlm.fast, mocap.fastrepr) compute what the numpy code computes.

Real motion: an HLM trained on three subject-35 walks follows a held-out walk with the left arm
and the head missing in bursts, once through the compiled step and once with LACUNA_NO_JIT=1;
every fill, std, style posterior and phase must agree to 1e-9, for the default (stream-cycle
adaptation, two-level offset), knots-only and faithful (kappa 0) filters, through a model's
state pool and through the daemon's batched seam (a batch of one, and a batch of several in one call, which
must give each stream the bits it gets alone); and the representation's
encoder/decoder alone, for both root modes, with and without normalisation."""
from __future__ import annotations

import numpy as np
import pytest

from hlm import fast
from mocap import fastrepr
from mocap.representation import Representation

pytestmark = pytest.mark.skipif(not fast.enabled(), reason="numba is not installed (or LACUNA_NO_JIT=1)")


@pytest.fixture(scope="module")
def walk(small_walk_hlm):
    from lacuna.modelfile import load_model
    from mocap.datasets import load_trial

    model = load_model(small_walk_hlm)
    channels = list(model.channels)
    test = load_trial("35_08").frames[:360]
    obs = np.ones(test.shape, bool)
    arm = [i for i, c in enumerate(channels) if c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "lhand", "head")]
    for start in (20, 140, 250):            # three bursts of the arm and head missing
        obs[start : start + 60, arm] = False
    obs[200:203] = False                    # and three frames missing whole
    return model, test, obs


def _run(model, frames, obs, monkeypatch, jit: bool, batch: bool = False):
    monkeypatch.setenv("LACUNA_NO_JIT", "0" if jit else "1")
    s = model.stream()
    out = []
    for t in range(frames.shape[0]):
        f = np.where(obs[t], frames[t], np.nan)
        fill = model.step_batch([s], f[None], obs[t][None])[0] if batch else s.step(f, obs[t])
        out.append((fill.frame.copy(), fill.std.copy(), np.array(fill.extras["style"]), fill.extras["phase"]))
    return out


@pytest.mark.parametrize("options", [dict(), dict(kappa_global=0.0), dict(kappa=0.0, kappa_global=0.0),
                                     dict(root_std=[])], ids=["default", "knots-only", "faithful", "summed-root-std"])
def test_compiled_step_equals_numpy_step(walk, monkeypatch, options):
    model, frames, obs = walk
    m = model.with_options(**options)
    assert fast.usable(m.tables)
    a = _run(m, frames, obs, monkeypatch, jit=True)
    b = _run(m, frames, obs, monkeypatch, jit=False)
    c = _run(m, frames, obs, monkeypatch, jit=True, batch=True)   # the daemon's path: step_batch of one
    for (fa, sa, ya, pa), (fb, sb, yb, pb), (fc, sc, _yc, _pc) in zip(a, b, c):
        np.testing.assert_allclose(fa, fb, rtol=0, atol=1e-9)
        np.testing.assert_allclose(sa, sb, rtol=0, atol=1e-9)
        np.testing.assert_allclose(ya, yb, rtol=0, atol=1e-9)
        assert abs(pa - pb) < 1e-9 or abs(abs(pa - pb) - 1.0) < 1e-9   # phase is circular
        np.testing.assert_array_equal(fa, fc)
        np.testing.assert_array_equal(sa, sc)
    # the fills are real fills: finite everywhere, and the missing arm (not a constant channel,
    # which is restored exactly) carries a positive std; observed values have none
    filled = np.array([f for f, _, _, _ in a])
    stds = np.array([s for _, s, _, _ in a])
    arm = [i for i, c in enumerate(model.channels) if c.split(".")[0] in ("lhumerus", "lradius")]
    assert np.isfinite(filled).all() and (stds[~obs] >= 0).all() and (stds[obs] == 0).all()
    assert (stds[20:80][:, arm] > 0).all()


@pytest.mark.parametrize("pick", ["contiguous", "scattered"])
def test_compiled_batch_equals_numpy_batch(walk, monkeypatch, pick):
    """step_batch over several streams (each from its own point of the walk), compiled stream by
    stream against the numpy batch path; "scattered" steps every other stream of the pool, so the
    seam gathers the state and hands the pool rows to the core."""
    model, frames, obs = walk
    T = frames.shape[0]
    offs = np.array([0, 37, 91, 150, 203, 260])
    results = {}
    for jit in (True, False):
        monkeypatch.setenv("LACUNA_NO_JIT", "0" if jit else "1")
        streams = [model.stream() for _ in offs]
        who = list(range(len(offs))) if pick == "contiguous" else [0, 2, 4]
        got = []
        for t in range(120):
            rows = (offs[who] + t) % T
            f = np.where(obs[rows], frames[rows], np.nan)
            fills = model.step_batch([streams[i] for i in who], f, obs[rows])
            got.append([(x.frame.copy(), x.std.copy(), x.extras["style"], x.extras["phase"]) for x in fills])
        results[jit] = got
    for a_t, b_t in zip(results[True], results[False]):
        for (fa, sa, ya, pa), (fb, sb, yb, pb) in zip(a_t, b_t):
            np.testing.assert_allclose(fa, fb, rtol=0, atol=1e-9)
            np.testing.assert_allclose(sa, sb, rtol=0, atol=1e-9)
            np.testing.assert_allclose(ya, yb, rtol=0, atol=1e-9)
            assert abs(pa - pb) < 1e-9 or abs(abs(pa - pb) - 1.0) < 1e-9


@pytest.mark.parametrize("options", [dict(), dict(kappa=0.0, kappa_global=0.0)], ids=["default", "faithful"])
def test_one_call_step_equals_three_calls_on_any_pool_row(walk, monkeypatch, options):
    """A lone stream through the seam (``step_batch`` of one) runs the whole step in one compiled
    call (``hlm.fast.step_slot``); a stream stepped by ``stream.step`` runs the encoder, filter
    and decoder as three.  Side by side, on rows 5 and 6 of a pool that grew (its arrays were
    reallocated under the streams), fed the same frames: the same bits, every frame."""
    model, frames, obs = walk
    m = model.with_options(**options)
    calls = []
    orig = fast.step_slot
    monkeypatch.setattr(fast, "step_slot", lambda *a, **k: calls.append(a[2]) or orig(*a, **k))
    others = [m.stream() for _ in range(5)]             # rows 0-4; the pool grows from 4 to 8
    one, three = m.stream(), m.stream()
    assert (one.slot, three.slot) == (5, 6) and m.pool.capacity == 8
    for t in range(frames.shape[0]):
        f = np.where(obs[t], frames[t], np.nan)
        a = m.step_batch([one], f[None], obs[t][None])[0]
        b = three.step(f, obs[t])
        np.testing.assert_array_equal(a.frame, b.frame)
        np.testing.assert_array_equal(a.std, b.std)
        np.testing.assert_array_equal(a.filled, b.filled)
        assert a.extras["style"] == b.extras["style"] and a.extras["phase"] == b.extras["phase"]
        if t == 100:  # a pool that grows mid-take moves every row's arrays: the next call must see the new ones
            others += [m.stream() for _ in range(3)]
            assert m.pool.capacity == 16
    assert calls == [5] * frames.shape[0]
    for o in others:  # the rows around them were never touched
        assert int(m.pool.core["t"][o.slot]) == 0


def test_filters_the_compiled_step_cannot_serve_take_the_numpy_path(walk):
    model, _, _ = walk
    assert not fast.usable(model.with_options(style_switch=1e-3).tables)
    assert not fast.usable(model.with_options(adapt_rate=0.01).tables)


def test_no_jit_switch(monkeypatch, walk):
    model, _, _ = walk
    monkeypatch.setenv("LACUNA_NO_JIT", "1")
    assert not fast.enabled() and not fast.usable(model.tables)


def test_where_written_memory_may_not_execute_the_numpy_path_serves(tmp_path, walk):
    """systemd's MemoryDenyWriteExecute (here the kernel's own W^X switch, prctl PR_SET_MDWE,
    inherited by nothing else) forbids a JIT: the process must step HLM on the numpy path
    instead of aborting."""
    import subprocess
    import sys

    model, frames, obs = walk
    model.save(str(tmp_path / "hlm.npz"))
    np.save(tmp_path / "f.npy", np.where(obs[:30], frames[:30], np.nan))
    code = f"""
import ctypes, sys
libc = ctypes.CDLL(None, use_errno=True)
if libc.prctl(65, 1, 0, 0, 0) != 0:   # PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN (Linux >= 6.3)
    print("no-mdwe"); sys.exit(0)
import numpy as np
from hlm import fast
from lacuna.modelfile import load_model
m = load_model({str(tmp_path / 'hlm.npz')!r})
s = m.stream()
for f in np.load({str(tmp_path / 'f.npy')!r}):
    fill = s.step(f)
print("enabled", fast.enabled(), "finite", bool(np.isfinite(fill.frame).all()))
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    if r.stdout.strip() == "no-mdwe":
        pytest.skip("this kernel has no PR_SET_MDWE (Linux < 6.3)")
    assert r.stdout.split() == ["enabled", "False", "finite", "True"]


STD_RULE = [0.5, 0.97, 0.07, 0.45, 0.3]   # a root_std rule ([a, p, c, w, u]) like hlm.methods.DEFAULTS


@pytest.mark.parametrize("root_mode,normalize,root_tau,root_power,root_turn,root_std",
                         [("relative", True, 0.0, 1.0, 0.0, []), ("relative", False, 0.0, 1.0, 0.0, []),
                          ("relative", False, 60.0, 1.0, 0.0, []), ("relative", True, 7.5, 2.0, 0.0, []),
                          ("relative", False, 0.0, 2.0, 200.0, []), ("relative", True, 40.0, 2.0, 200.0, []),
                          ("relative", True, 40.0, 2.0, 200.0, STD_RULE), ("relative", False, 0.0, 1.0, 0.0, STD_RULE),
                          ("raw", True, 0.0, 1.0, 0.0, []), ("raw", False, 0.0, 1.0, 0.0, [])])
def test_compiled_representation_equals_numpy(data, root_mode, normalize, root_tau, root_power, root_turn, root_std):
    """encode -> (a model's fill) -> decode -> commit, frame by frame over a real walk whose root and
    arm drop out: the compiled single-stream code and ReprState agree to 1e-9 in the features, the
    feature mask, the completed frame, the raw std and the carried state (unwrapped angles, yaw,
    the root's dropout count, summed stds and averaged yaw rate), with and without the root damping
    (fixed, and growing with the observed turning: root_turn), with the summed root std and the
    fitted rule (root_std)."""
    from mocap.datasets import load_trial

    walks = [load_trial(t) for t in ("35_01", "35_06")]
    rep = Representation.fit([m.frames for m in walks], walks[0].channels, root_mode=root_mode, normalize=normalize,
                             root_tau=root_tau, root_power=root_power, root_turn=root_turn, root_turn_frames=30.0,
                             root_std=root_std)
    frames = load_trial("35_08").frames[:300]
    C, F = frames.shape[1], rep.n_features
    obs = np.ones(frames.shape, bool)
    root = [i for i, c in enumerate(walks[0].channels) if c.startswith("root.")]
    arm = [i for i, c in enumerate(walks[0].channels) if c.startswith(("lhumerus", "lradius"))]
    obs[40:90, arm] = False
    obs[120:150, root] = False            # the root itself lost: relative features go missing
    obs[200:202] = False
    obs[240:260, root[:2]] = False        # part of the root: tx, ty
    rng = np.random.default_rng(1)
    a, b = rep.new_state(1), rep.new_state(1)
    rate_before = 0.0
    for t in range(frames.shape[0]):
        f, o = np.where(obs[t], frames[t], np.nan)[None], obs[t][None]
        za, oa = a.encode(f, o)
        zb, ob = fastrepr.encode(b, f, o)
        np.testing.assert_array_equal(oa, ob)
        np.testing.assert_allclose(za, zb, rtol=0, atol=1e-9)
        # what a model would hand back: every feature filled, a std where it was missing
        zfill = np.where(oa, za, rng.normal(size=(1, F)))
        zstd = np.where(oa, 0.0, rng.uniform(0.1, 1.0, size=(1, F)))
        done_a, std_a = a.finish(zfill, zstd, f, o)
        done_b, std_b = fastrepr.finish(b, zfill, zstd, f, o)
        np.testing.assert_allclose(done_a, done_b, rtol=0, atol=1e-9)
        np.testing.assert_allclose(std_a, std_b, rtol=0, atol=1e-12)
        for attr in ("prev_u", "prev_raw", "prev_yaw", "root_st"):
            np.testing.assert_allclose(getattr(a, attr), getattr(b, attr), rtol=0, atol=1e-9)
        assert a.started[0] and b.started[0]
        if root_mode == "relative" and 120 <= t < 150:
            assert a.root_st[0, 0] == t - 119     # the root's gap is counted
        if root_mode == "relative" and t == 119:
            assert a.root_st[0, 3] != 0.0          # the yaw rate is averaged while the root is seen
            rate_before = float(a.root_st[0, 3])
        if root_mode == "relative" and 120 <= t < 150:
            assert a.root_st[0, 3] == rate_before  # and frozen over its gap
    assert C == len(walks[0].channels)


@pytest.mark.parametrize("options", [dict(), dict(kappa=0.0, kappa_global=0.0)], ids=["default", "faithful"])
def test_a_batch_in_one_call_equals_each_stream_alone(walk, monkeypatch, options):
    """A tick of several streams runs encoder, filter and decoder of all of them in one compiled
    call on their pool rows (``hlm.fast.step_rows_arrays``, under ``step_rows``), sharing the filter's working arrays; each
    stream stepped alone (``step_batch`` of one: ``step_slot``, its own arrays) is its reference.
    Streams handed over in a scrambled order, on pool rows that are not contiguous (every other
    row of a pool that grows mid-take): the same bits, every stream, every frame; and the rows
    between them are never touched."""
    model, frames, obs = walk
    m = model.with_options(**options)
    T = frames.shape[0]
    offs = np.array([0, 91, 37, 203, 150])
    pool_a = [m.stream() for _ in range(2 * len(offs))]     # the batch takes rows 0, 2, 4, ...
    batch = pool_a[::2]
    alone = [m.stream() for _ in offs]
    order = [3, 0, 4, 1, 2]                                  # handed over out of slot order
    calls = []
    orig = fast.step_rows_arrays
    monkeypatch.setattr(fast, "step_rows_arrays", lambda *a, **k: calls.append(list(a[2])) or orig(*a, **k))
    for t in range(150):
        rows = (offs + t) % T
        f = np.where(obs[rows], frames[rows], np.nan)
        got = m.step_batch([batch[i] for i in order], f[order], obs[rows][order])
        for j, i in enumerate(order):
            ref = m.step_batch([alone[i]], f[i : i + 1], obs[rows[i]][None])[0]
            np.testing.assert_array_equal(got[j].frame, ref.frame)
            np.testing.assert_array_equal(got[j].std, ref.std)
            np.testing.assert_array_equal(got[j].filled, ref.filled)
            assert got[j].extras == ref.extras
        if t == 60:  # the pool grows: every row's arrays move; the next call must see the new ones
            pool_a += [m.stream() for _ in range(m.pool.capacity - m.pool.in_use + 1)]
    assert calls == [[batch[i].slot for i in order]] * 150     # one call a tick, the rows as handed over
    t_rows = m.pool.core["t"]
    assert [int(t_rows[s.slot]) for s in batch] == [150] * len(batch)
    assert all(int(t_rows[s.slot]) == 0 for s in pool_a[1::2])
    # the fills are real: the arm missing from frame 20 to 80 is filled with a positive std
    arm = [i for i, c in enumerate(m.channels) if c.split(".")[0] in ("lhumerus", "lradius")]
    assert np.isfinite(got[0].frame).all()
    assert ((got[0].std[arm] > 0) == ~obs[(offs[order[0]] + 149) % T][arm]).all()


def test_step_block_is_step_batch_as_arrays(walk, monkeypatch):
    """``step_block`` (the daemon's bundle path) returns what ``step_batch`` returns, as arrays
    written by the one compiled call: the same bits in every fill, std, filled mask, style
    posterior and phase, streams on scrambled, non-contiguous rows; one stream, and a level,
    go through step_batch's Fills stacked."""
    model, frames, obs = walk
    a, b = model.with_options(), model.with_options()      # two models: two pools, one the reference
    offs = np.array([0, 91, 37, 203, 150])
    order = [3, 0, 4, 1, 2]
    sa = [a.stream() for _ in range(2 * len(offs))][::2]
    sb = [b.stream() for _ in range(2 * len(offs))][::2]
    calls = []
    orig = fast.step_rows_arrays
    monkeypatch.setattr(fast, "step_rows_arrays", lambda *x, **k: calls.append(1) or orig(*x, **k))
    T = frames.shape[0]
    for t in range(120):
        rows = (offs + t) % T
        f, o = np.where(obs[rows], frames[rows], np.nan)[order], obs[rows][order]
        ref = a.step_batch([sa[i] for i in order], f, o)
        got = b.step_block([sb[i] for i in order], f, o)
        assert isinstance(got.style, np.ndarray) and isinstance(got.phase, np.ndarray) and got.degraded is None
        for j, fl in enumerate(ref):
            np.testing.assert_array_equal(got.frame[j], fl.frame)
            np.testing.assert_array_equal(got.std[j], fl.std)
            np.testing.assert_array_equal(got.filled[j], fl.filled)
            assert got.style[j].tolist() == fl.extras["style"] and got.phase[j] == fl.extras["phase"]
    assert len(calls) == 2 * 120                              # each path one compiled call a tick
    one = b.step_block([sb[0]], f[:1], o[:1])                 # one stream: step_batch's Fill, stacked
    ref1 = a.step_batch([sa[0]], f[:1], o[:1])[0]
    np.testing.assert_array_equal(one.frame[0], ref1.frame)
    assert one.style == [ref1.extras["style"]] and one.degraded == [False]
    with pytest.raises(ValueError, match="same stream twice"):
        b.step_block([sb[0], sb[0]], f[:2], o[:2])


def test_a_batch_refuses_rows_outside_the_pool_and_a_stream_twice(walk):
    """Compiled code has no bounds checks: a pool row outside the pool is refused before the
    call, and the seam refuses the same stream twice in one batch."""
    model, frames, obs = walk
    s = [model.stream() for _ in range(3)]
    tabs = fast.slot_tables(model.tables, model.representation)
    f = np.where(obs[:2], frames[:2], np.nan)
    with pytest.raises(IndexError, match="pool rows"):
        fast.step_rows(tabs, model.pool, np.array([s[0].slot, model.pool.capacity]), f, obs[:2])
    with pytest.raises(IndexError, match="pool rows"):
        fast.step_rows(tabs, model.pool, np.array([-1, s[1].slot]), f, obs[:2])
    with pytest.raises(ValueError, match="same stream twice"):
        model.step_batch([s[2], s[2]], f, obs[:2])
    assert all(int(model.pool.core["t"][x.slot]) == 0 for x in s)   # nothing was stepped


def test_read_only_frames_from_the_wire_compile_no_second_kernel(walk):
    """A bundle decoded from the wire arrives as read-only arrays; numba types those apart from
    writable ones, and a call with them would compile a second kernel inside the live path (it
    cost a benchmark run most of a repeat's frames).  The seam hands the compiled steps writable
    copies: the same bits as writable input, no new signature, one stream or several."""
    model, frames, obs = walk
    for n in (1, 3):
        a = [model.stream() for _ in range(n)]
        b = [model.stream() for _ in range(n)]
        kernels = (fast._step_rows, fast._step_slot, fast._step_many, fastrepr.encode_many, fastrepr.finish_many)
        for t in range(40):
            f = np.where(obs[t : t + n], frames[t : t + n], np.nan)
            fa = model.step_batch(a, f, obs[t : t + n])
            before = sum(len(k.signatures) for k in kernels)
            ro_f = np.frombuffer(f.tobytes(), dtype=np.float64).reshape(f.shape)
            ro_o = np.frombuffer(obs[t : t + n].tobytes(), dtype=bool).reshape(f.shape)
            assert not ro_f.flags.writeable and not ro_o.flags.writeable
            fb = model.step_batch(b, ro_f, ro_o)
            assert sum(len(k.signatures) for k in kernels) == before >= 1
            for x, y in zip(fa, fb):
                np.testing.assert_array_equal(x.frame, y.frame)
                np.testing.assert_array_equal(x.std, y.std)
                assert x.extras == y.extras


def test_the_compiled_angle_wrap_is_the_float_modulo_to_the_bit():
    """``fastrepr._wrap`` skips the float modulo within a turn either way; on angles of every
    range, turn boundaries, signed zeros, tiny and huge values, NaN and infinities it returns
    what ``(x + 180) % 360 - 180`` returns in Python, bit for bit."""
    rng = np.random.default_rng(3)
    edges = [0.0, -0.0, 180.0, -180.0, 540.0, -540.0, 360.0, -360.0, 900.0, -900.0, 1e-300, -1e-300, 1e-20, -1e-20,
             179.99999999999997, -180.00000000000003, 539.9999999999999, 1e300, -1e300]
    xs = np.concatenate([rng.uniform(-200, 200, 4000), rng.uniform(-2000, 2000, 4000), edges,
                         np.nextafter(np.array(edges), np.inf), np.nextafter(np.array(edges), -np.inf)])
    for x in xs.tolist():
        got, want = fastrepr._wrap(x), (x + 180.0) % 360.0 - 180.0
        assert np.float64(got).tobytes() == np.float64(want).tobytes(), (x, got, want)
    for x in (np.nan, np.inf, -np.inf):
        assert np.isnan(fastrepr._wrap(x))
