"""``default``'s long_ll (blend/withhlm.py, "long_ll"; bench/notebook/loco-13.md): in a long erasure (more
than SHADOW_MAX_MISS channels missing, every leg channel observed) the HLM's one-step predictive
log-likelihood of the legs it still sees (its forward step's normaliser, kept per stream by hlm.online /
hlm.fast) is tracked against the level the stream had while its HLM share was earned; a fall of more than
D nats a feature revokes the share (the last q bin) for the rest of the erasure.  On real takes, the experts
trained small (as tests/test_default_long_gate.py does): the revoke fires on a walk -> seated splice and not
on a walk that goes on; off is the fill without it bit for bit until the revoke; numpy == compiled ==
step_block; the predictive likelihood itself numpy == compiled; the setting's file round trip."""
from __future__ import annotations

import math

import numpy as np
import pytest
from default_small import remix, train_small

from blend import withhlm
from blend.withhlm import WithHLMModel
from lacuna import jit, modelfile
from lacuna.filler import FillerError, Model
from mocap import protocols, splits

pytestmark = pytest.mark.realdata

LL = (4.0, 30.0)


@pytest.fixture(scope="module")
def model(data):
    return train_small()


def _twin(model, ll=None, compiled=True) -> WithHLMModel:
    """The model's experts mixed anew, long_ll set to ``ll`` (None: off)."""
    return remix(model, {"long_ll": list(ll)} if ll else {}, compiled)


def _case(channels, walk, other):
    """``walk``'s first 5 s (at most) then ``other``'s first 1500 frames, everything but the legs erased from
    30 frames after the seam (bench/loco12_regime.py's regime); ``other`` None: the walk goes on, erased
    from half way.  (frames, observed, the erasure's onset)"""
    w = np.array(splits.load_take(walk).frames)
    if other is None:
        x, onset = w, len(w) // 2
    else:
        w = w[:600]
        n = splits.load_take(other).frames[:1500].copy()
        pos = [j for j, c in enumerate(channels) if c.startswith("root.t")]
        n[:, pos] += w[-1, pos] - n[0, pos]
        x, onset = np.concatenate([w, n]), len(w) + 30
    legs = np.isin(withhlm.group_index(list(channels)), withhlm.LEG_GROUPS)
    obs = np.ones(x.shape, bool)
    obs[onset:, ~legs] = False
    return x, obs, onset


def _run(model, x, obs, ll, compiled=True):
    """Fills, std, final state and q bin per frame; the stream's ordinary bound held at q+ = 0.5 (the HLM's
    share earned, as after a walk) on every frame: only long_ll can take it away in the erasure."""
    m = _twin(model, ll, compiled)
    st = m.stream()
    out, std, qb = np.empty_like(x), np.empty_like(x), []
    for t in range(len(x)):
        st._lq = math.log(0.5)
        f = st.step(np.where(obs[t], x[t], np.nan), obs[t])
        out[t], std[t] = f.frame, f.std
        qb.append(m._qb(st, obs[t]))
    return out, std, st, np.array(qb)


def test_revoke_fires_on_a_walk_that_stops(model):
    """walking_21 then the seated 49_19, the upper body erased from 30 frames after the seam: the legs'
    predictive likelihood falls below the walk's and the share goes (the last q bin from the revoke on, in
    the regime only after LL_N0 frames); before it, the fill without long_ll bit for bit."""
    x, obs, onset = _case(model.channels, "walking_21", "49_19")
    off, soff, _, qoff = _run(model, x, obs, None)
    on, son, st, qb = _run(model, x, obs, LL)
    last = len(withhlm.Q_EDGES)
    assert st.n_llrev == 1 and st.ll_rev and math.isfinite(st.ll_B)
    assert st.ll_S / st.ll_N < st.ll_B - LL[0]
    # (up to the onset an ordinary window may close and set q+ for that frame; it is held again the next)
    t_rev = onset + 1 + int(np.flatnonzero(qb[onset + 1:] == last)[0])
    assert (qoff[onset + 1:] < last).all()
    assert onset + withhlm.LL_N0 - 1 <= t_rev and (qb[t_rev:] == last).all()
    np.testing.assert_array_equal(on[:t_rev], off[:t_rev])
    np.testing.assert_array_equal(son[:t_rev], soff[:t_rev])
    assert np.abs(on[t_rev:] - off[t_rev:]).max() > 1e-3


def test_no_revoke_on_a_walk_that_goes_on(model):
    """35_30 walking on under the same erasure: the level stays within D of the baseline, no revoke, the
    fill is the fill without long_ll bit for bit; and a gaps stream (the regime never reached)."""
    x, obs, _ = _case(model.channels, "35_30", None)
    off, soff, _, _ = _run(model, x, obs, None)
    on, son, st, _ = _run(model, x, obs, LL)
    assert st.n_llrev == 0 and st.ll_in and st.ll_S / st.ll_N > st.ll_B - LL[0]
    np.testing.assert_array_equal(on, off)
    np.testing.assert_array_equal(son, soff)
    case = next(iter(protocols.Gaps(seed=0, split="validation").cases()))
    a, sa, _, _ = _run(model, case.truth, case.observed, None)
    b, sb, stb, _ = _run(model, case.truth, case.observed, LL)
    assert stb.n_llrev == 0
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(sa, sb)


def test_predictive_likelihood_numpy_is_compiled(model):
    """The HLM's kept normaliser (hlm.online.init_state's "ll"): the compiled step's equals the numpy
    reference's, frame by frame, fully observed and legs only."""
    if not jit.enabled():
        pytest.skip("numba off: one path only")
    from hlm import fast

    h = model.hlm
    x, obs, onset = _case(model.channels, "walking_21", "49_19")
    x, obs = x[onset - 100:onset + 100], obs[onset - 100:onset + 100]
    st = h.stream()
    ref = {k: v[st.slot:st.slot + 1].copy() for k, v in h.pool.core.items()}
    rs = h.representation.new_state(1)
    for t in range(len(x)):
        f = np.ascontiguousarray(np.where(obs[t], x[t], np.nan)[None])
        h.step_batch([st], f, np.ascontiguousarray(obs[t][None]))
        z, zo = rs.encode(f, obs[t][None])
        from hlm import online
        online.update(h.tables, ref, z, zo, want_ll=False)
        got = h.pool.core["ll"][st.slot]
        assert got[1] == ref["ll"][0, 1] == zo.sum() and abs(got[0] - ref["ll"][0, 0]) < 1e-8 * (1 + abs(got[0]))
        rs.finish(np.where(zo, z, 0.0), np.zeros_like(z), f, obs[t][None])
    assert fast.usable(h.tables)


def test_numpy_compiled_and_block_agree(model):
    """The revoke on the splice: the numpy mixing, the compiled one and the daemon's block path
    (``_step_block`` against ``step_batch``'s Fills stacked, 2 streams at different offsets) give the same
    fills and revoke at the same frame."""
    if not jit.enabled():
        pytest.skip("numba off: one path only")
    x, obs, _ = _case(model.channels, "walking_21", "49_19")
    a, sa, st_a, qa = _run(model, x, obs, LL, compiled=True)
    b, sb, st_b, qb = _run(model, x, obs, LL, compiled=False)
    assert (qa == qb).all() and st_a.n_llrev == st_b.n_llrev == 1
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sa, sb, rtol=0, atol=1e-9)
    m = _twin(model, LL)
    s1, s2 = [m.stream(), m.stream()], [m.stream(), m.stream()]
    for t in range(len(x)):
        for s in s1 + s2:
            s._lq = math.log(0.5)
        rows = [t, max(t - 40, 0)]
        f, o = np.ascontiguousarray(np.where(obs[rows], x[rows], np.nan)), np.ascontiguousarray(obs[rows])
        p = Model.step_block(m, s1, f, o)
        q = m.step_block(s2, f, o)
        np.testing.assert_array_equal(p.frame, q.frame)
        np.testing.assert_array_equal(p.std, q.std)
    assert [s.n_llrev for s in s1] == [s.n_llrev for s in s2] == [1, 1]


def test_setting_and_file_round_trip(model, tmp_path):
    """Trained models carry LONG_LL; a set long_ll survives the file; a file without the key loads off; a
    malformed one is a ModelFileError naming it; bad values a FillerError."""
    assert model.long_ll == withhlm.LONG_LL
    m = _twin(model)
    assert m.long_ll == withhlm.LONG_LL_OFF == (0.0, 0.0) and not m._ll_on
    p = tmp_path / "m.npz"
    m.save(str(p))
    assert "long_ll" not in modelfile.load_arrays(str(p))[0]
    assert modelfile.load_model(str(p)).long_ll == withhlm.LONG_LL_OFF
    m.set_long_ll(*LL)
    m.save(str(p))
    assert modelfile.load_arrays(str(p))[0]["long_ll"] == list(LL)
    assert modelfile.load_model(str(p)).long_ll == LL
    m.set_long_ll(*withhlm.LONG_LL_OFF)
    assert "long_ll" not in m.meta and not m._ll_on
    meta, arrays = modelfile.load_arrays(str(p))
    for bad in ("x", [4.0], [4.0, "30"], [-1.0, 30.0], [4.0, 0.0], [4.0, math.inf], [True, 30.0], [4.0, 30.0, 1.0]):
        modelfile.save_arrays(str(p), {**meta, "long_ll": bad}, arrays)
        with pytest.raises(modelfile.ModelFileError, match="long_ll"):
            modelfile.load_model(str(p))
    with pytest.raises(FillerError, match="long_ll"):
        m.set_long_ll(math.nan, 30.0)
