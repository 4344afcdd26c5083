"""The HLM filter's per-state tables hold float32 values (issue 19, bench/notebook/hlm64-12.md):
rounded once when the tables are built, read as float32 by the compiled step and as the same
values in float64 by the numpy reference, while the model's parameters (and so its files) stay
float64.  The compiled step with the float32 copies gives what it gives with those values in
float64 arrays (the same arithmetic on the same numbers), and the kappa = 0 fill's ``pack`` is the
products of the rounded tables."""
from __future__ import annotations

import numpy as np
import pytest

from hlm import fast
from hlm.emissions import single


@pytest.fixture(scope="module")
def model(small_walk_hlm):
    from lacuna.modelfile import load_model

    return load_model(small_walk_hlm)


def _is_f32(a: np.ndarray) -> bool:
    return a.dtype == np.float64 and np.array_equal(a, a.astype(np.float32).astype(np.float64))


def test_the_tables_hold_float32_values_and_the_parameters_do_not(model, small_walk_hlm):
    tab = model.tables
    for name, a in (("fused_t", tab.em.fused_t), ("fused", tab.em.fused), ("mu", tab.mu),
                    ("lam_rows", tab.lam_rows), ("var_q", tab.var_q)):
        assert _is_f32(a), name
        assert a.flags.c_contiguous, name
    np.testing.assert_array_equal(tab.em.fused, tab.em.fused_t.T)
    for name in ("fused_t", "mu", "lam_rows", "var_q"):
        q = tab.f32[name]
        assert q.dtype == np.float32 and q.flags.c_contiguous
        np.testing.assert_array_equal(q.astype(np.float64), tab.em.fused_t if name == "fused_t" else getattr(tab, name))
    F = tab.mu.shape[1]
    pack = tab.pack
    np.testing.assert_array_equal(pack[:, :F], tab.lam_rows * tab.mu)
    np.testing.assert_array_equal(pack[:, F : 2 * F], tab.lam_rows)
    np.testing.assert_array_equal(pack[:, 2 * F : 3 * F], tab.mu)
    np.testing.assert_array_equal(pack[:, 3 * F :], tab.mu * tab.mu + tab.var_q)
    # the model's parameters are not rounded: a file written again holds what was loaded
    assert not _is_f32(model.params.mu.reshape(-1, F))
    from lacuna.modelfile import load_model
    again = load_model(small_walk_hlm)
    np.testing.assert_array_equal(again.params.mu, model.params.mu)
    np.testing.assert_array_equal(again.tables.mu, tab.mu)     # (rounding is a function of the parameters)
    assert np.array_equal(single(tab.mu), tab.mu)               # idempotent


@pytest.mark.skipif(not fast.enabled(), reason="numba is not installed (or LACUNA_NO_JIT=1)")
def test_the_compiled_step_reads_the_same_values_as_float32(model):
    """64 streams at different phases through ``step_rows_arrays`` twice from the same pool state:
    once with the float32 tables (``slot_tables``), once with them upcast to float64 arrays."""
    from mocap.datasets import load_trial

    frames = load_trial("35_08").frames[:, load_trial("35_08").index(list(model.channels))].astype(np.float64)
    T, C = frames.shape
    arm = np.array([c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "lhand") for c in model.channels])
    n = 64
    streams = [model.stream() for _ in range(n)]
    rows = np.array([s.slot for s in streams], dtype=np.int64)
    rt, ht, zero = fast.slot_tables(model.tables, model.representation)
    assert all(a.dtype == np.float32 for a in (ht[3], ht[4], ht[11], ht[12]))
    ht64 = tuple(a.astype(np.float64) if isinstance(a, np.ndarray) and a.dtype == np.float32 else a for a in ht)
    pool = model.pool
    offsets = (np.arange(n) * (T // n)) % T
    for t in range(60):
        idx = (offsets + t) % T
        obs = np.ones((n, C), bool)
        obs[:, arm] = t % 30 >= 10
        f = np.where(obs, frames[idx], np.nan)
        saved = {k: v.copy() for k, v in {**pool.core, **pool.repr}.items()}
        a = fast.step_rows_arrays((rt, ht, zero), pool, rows, f, obs, cond=model.cond)
        after = {k: v.copy() for k, v in {**pool.core, **pool.repr}.items()}
        for k, v in saved.items():
            (pool.core if k in pool.core else pool.repr)[k][...] = v
        b = fast.step_rows_arrays((rt, ht64, zero), pool, rows, f, obs, cond=model.cond)
        for x, y in zip(a, b):
            np.testing.assert_allclose(x, y, rtol=0, atol=1e-12)
        for k, v in after.items():
            np.testing.assert_allclose((pool.core if k in pool.core else pool.repr)[k], v, rtol=0, atol=1e-12)
