"""long_ll's legs-only baseline (``long_ll_legs``, blend/withhlm.py; bench/notebook/loco-14.md): the HLM's "ll"
row's columns 2-3, the forward normaliser over the observed leg features only on the same support, numpy ==
compiled on every path; files without the key compute nothing new and fill as before; with it the baseline
and the erasure's level are the same quantity, so a walk whose upper body the HLM predicts badly (its
whole-body baseline far below its legs') is still revoked when the performer stops.  TRAIN takes only, the
experts trained small (tests/default_small.py)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from default_small import remix, train_small

from blend import withhlm
from lacuna import jit, modelfile
from lacuna.filler import FillerError
from mocap import splits

pytestmark = pytest.mark.realdata

LL = (4.0, 60.0)


@pytest.fixture(scope="module")
def model(data):
    return train_small()


def _legs(model) -> np.ndarray:
    return np.isin(withhlm.group_index(list(model.channels)), withhlm.LEG_GROUPS)


def _masks(model, T: int) -> np.ndarray:
    """(T, C) observed masks cycling every 25 frames: all, the legs only, 20% missing at random, the legs
    and one leg channel missing, nothing."""
    legs, C = _legs(model), len(model.channels)
    rng = np.random.default_rng(3)
    out = np.ones((T, C), bool)
    for t in range(T):
        k = (t // 25) % 5
        if k == 1:
            out[t] = legs
        elif k == 2:
            out[t] = rng.random(C) > 0.2
        elif k == 3:
            out[t] = legs
            out[t, np.flatnonzero(legs)[t % legs.sum()]] = False
        elif k == 4:
            out[t] = False
    return out


def test_legs_columns_numpy_is_compiled(model):
    """Columns 2-3 (and 0-1) of the "ll" row: the compiled lone step (step_slot), the daemon's block path
    (_step_rows) and the batched compiled step (_step_many) equal the numpy reference (_update_one, update)
    frame by frame; the count is the observed leg features; 0, 0 with no leg feature observed."""
    if not jit.enabled():
        pytest.skip("numba off: one path only")
    from hlm import fast, online

    h = model.hlm
    lf = h.leg_feats(np.flatnonzero(_legs(model)))
    assert 0 < lf.size < h.representation.n_features
    h.set_ll_feats(lf)
    assert fast.usable(h.tables)
    x = np.array(splits.load_take("walking_13").frames)[:250]
    O = _masks(model, len(x))
    # the lone compiled stream and the block path (two streams 40 frames apart) against numpy's lone update
    lone, pair = h.stream(), [h.stream(), h.stream()]
    refs = [{k: v[s.slot:s.slot + 1].copy() for k, v in h.pool.core.items()} for s in [lone] + pair]
    reps = [h.representation.new_state(1) for _ in refs]
    for t in range(len(x)):
        rows = [t, t, max(t - 40, 0)]
        f = np.ascontiguousarray(np.where(O[rows], x[rows], np.nan))
        o = np.ascontiguousarray(O[rows])
        h.step_batch([lone], f[:1].copy(), o[:1].copy())
        h.step_block(pair, f[1:].copy(), o[1:].copy())
        for i, (s, ref, rs) in enumerate(zip([lone] + pair, refs, reps, strict=True)):
            z, zo = rs.encode(f[i:i + 1], o[i:i + 1])
            online.update(h.tables, ref, z, zo, want_ll=False)
            got, want = h.pool.core["ll"][s.slot], ref["ll"][0]
            assert got[1] == want[1] == zo.sum() and got[3] == want[3] == zo[0, lf].sum()
            for c in (0, 2):
                assert abs(got[c] - want[c]) < 1e-8 * (1 + abs(want[c])), (t, i, c, got, want)
            if want[3] == 0:
                assert got[2] == want[2] == 0.0
            rs.finish(np.where(zo, z, 0.0), np.zeros_like(z), f[i:i + 1], o[i:i + 1])
    # the batched paths on the features: hlm.fast.step (_step_many) against hlm.online.update (n = 3)
    tab = h.tables
    Z = h.representation.transform(x, normalized=True)
    zo3 = np.stack([h.representation.feature_observed(O[(np.arange(len(x)) + 13 * i) % len(x)]) for i in range(3)], 1)
    sn, sc = online.init_state(tab, 3), online.init_state(tab, 3)
    for t in range(len(x)):
        z = Z[(t + np.arange(3) * 50) % len(x)]
        online.update(tab, sn, z, zo3[t], want_ll=False)
        fast.step(tab, sc, z, zo3[t])
        np.testing.assert_array_equal(sc["ll"][:, [1, 3]], sn["ll"][:, [1, 3]])
        np.testing.assert_allclose(sc["ll"][:, [0, 2]], sn["ll"][:, [0, 2]], rtol=1e-8, atol=1e-8)
        np.testing.assert_array_equal(sn["ll"][:, 3], zo3[t][:, lf].sum(1))


def _splice(model, walk: str, other: str, upper_off: float = 0.0):
    """``walk``'s first 600 frames (every channel outside the legs and the root shifted by ``upper_off``
    degrees: an upper body the HLM predicts badly), then ``other``'s first 900, root translation continued;
    everything but the legs erased from 30 frames after the seam (bench/loco12_regime.py's regime)."""
    ch = list(model.channels)
    legs = _legs(model)
    w = np.array(splits.load_take(walk).frames)[:600].copy()
    n = np.array(splits.load_take(other).frames)[:900].copy()
    pos = [j for j, c in enumerate(ch) if c.startswith("root.t")]
    n[:, pos] += w[-1, pos] - n[0, pos]
    w[:, ~legs & np.array([not c.startswith("root") for c in ch])] += upper_off
    x = np.concatenate([w, n])
    obs = np.ones(x.shape, bool)
    obs[len(w) + 30:, ~legs] = False
    return x, obs


def _run(m, x, obs):
    """Fills and the final stream, the ordinary bound held at q+ = 0.5 (the HLM's share earned) every frame."""
    st = m.stream()
    out = np.empty_like(x)
    for t in range(len(x)):
        st._lq = math.log(0.5)
        out[t] = st.step(np.where(obs[t], x[t], np.nan), obs[t]).frame
    return out, st


def test_legs_baseline_revokes_where_whole_body_does_not(model):
    """walking_13 with its upper body shifted 30 degrees, then basketball_1, erased but the legs: the
    whole-body baseline (loco-13) sinks with the badly predicted upper body and the stop is not revoked; the
    legs' baseline is the walk's legs, the stop's legs fall far below it and the share is revoked."""
    x, obs = _splice(model, "walking_13", "basketball_1", 30.0)
    _, whole = _run(remix(model, {"long_ll": list(LL)}), x, obs)
    _, legs = _run(remix(model, {"long_ll": list(LL), "long_ll_legs": True}), x, obs)
    assert math.isfinite(whole.ll_B) and math.isfinite(legs.ll_B)
    assert whole.n_llrev == 0 and legs.n_llrev == 1 and legs.ll_rev
    assert legs.ll_B > whole.ll_B + 20.0   # the legs' baseline is not the whole body's
    assert legs.ll_S / legs.ll_N < legs.ll_B - LL[0]


def test_files_without_the_key_fill_as_before(model, tmp_path):
    """A file without ``long_ll_legs`` loads with it off, its HLM computes no legs' columns (they stay 0), and
    its fills equal those of the same file whose HLM does compute them (they change nothing else it reads);
    the key survives the file; a malformed one is a ModelFileError naming it, a bad value a FillerError."""
    p = tmp_path / "m.npz"
    remix(model, {"long_ll": list(LL)}).save(str(p))
    meta = modelfile.load_arrays(str(p))[0]
    assert "long_ll_legs" not in meta and meta["long_ll"] == list(LL)
    a = modelfile.load_model(str(p))
    assert not a.long_ll_legs and a._ll_c == 0 and a.hlm.tables.ll_feats.size == 0
    x, obs = _splice(model, "walking_13", "basketball_1")
    fa, sa = _run(a, x, obs)
    assert not a.hlm.pool.core["ll"][:, 2:].any()
    b = modelfile.load_model(str(p))
    b.hlm.set_ll_feats(b.hlm.leg_feats(b._legs))   # the legs' columns computed, the flag off
    fb, sb = _run(b, x, obs)
    assert b.hlm.pool.core["ll"][:, 3].any()
    np.testing.assert_array_equal(fa, fb)
    assert sa.n_llrev == sb.n_llrev and sa.ll_B == sb.ll_B
    b.set_long_ll_legs(True)
    b.save(str(p))
    assert modelfile.load_arrays(str(p))[0]["long_ll_legs"] is True
    c = modelfile.load_model(str(p))
    assert c.long_ll_legs and c._ll_c == 2 and c.hlm.tables.ll_feats.size > 0
    c.set_long_ll_legs(False)
    assert "long_ll_legs" not in c.meta and c._ll_c == 0
    meta, arrays = modelfile.load_arrays(str(p))
    for bad in (1, "yes", [True], None):
        modelfile.save_arrays(str(p), {**meta, "long_ll_legs": bad}, arrays)
        with pytest.raises(modelfile.ModelFileError, match="long_ll_legs"):
            modelfile.load_model(str(p))
    with pytest.raises(FillerError, match="long_ll_legs"):
        c.set_long_ll_legs(0)  # type: ignore[arg-type]
