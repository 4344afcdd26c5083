"""The conditional fill on the filter's support (hlm.condfill.correct1 over the states
hlm.fast._step_in found, ~20 of 560) gives the bits of the kernel it replaced, which visited all
C*M states.

The replaced kernel is kept below verbatim (hlm/condfill.py's ``correct1`` at 2968ff8) and put
into copies of the daemon's two compiled steps (``hlm.fast._step_rows``: a bundle;
``_step_slot``: one stream) in place of the new one; real CMU motion (an HLM with its conditional
fill trained on three subject-35 walks, the held-out 35_08 with the left arm missing in bursts and,
over its second half, everything but the legs) goes through the real step and the reference step,
and every fill, std, style posterior and phase must be the same bits: 64 streams bundled at
scattered offsets (step_block), and one stream (step_batch of one)."""
from __future__ import annotations

import types

import numpy as np
import pytest

from hlm import condfill, fast
from hlm.methods import train_model

numba = pytest.importorskip("numba")
pytestmark = pytest.mark.skipif(not fast.enabled(), reason="numba is not installed (or LACUNA_NO_JIT=1)")


@numba.njit(nogil=True)
def _chol_solve(A, b):  # pragma: no cover - compiled
    """The old kernel's solver (``_chol_solve`` at 2968ff8, which allocated its L, y, x): production's
    in-place one, the same operations in the same order, given arrays of its own."""
    n = A.shape[0]
    return condfill._chol_solve_in(A, b, np.zeros((n, n)), np.empty(n), np.empty(n))


def _correct1_old(post, z, zobs, zf, M, mu, bin0, bin1, bin_a, kappa, kappa_g, D, W, G, GW, lam_rows, pack,
                  cov, prec, shrink, live, style_live):  # pragma: no cover - compiled
    # hlm/condfill.py's correct1 at 2968ff8, verbatim: every one of the C*M states visited
    F = z.shape[0]
    no = 0
    for f in range(F):
        if zobs[f]:
            no += 1
    nm = F - no
    if no == 0 or nm == 0:
        return
    oi = np.empty(no, np.int64)
    mi = np.empty(nm, np.int64)
    a_ = 0
    b_ = 0
    for f in range(F):
        if zobs[f]:
            oi[a_] = f
            a_ += 1
        else:
            mi[b_] = f
            b_ += 1
    CM = post.shape[0]
    pmax = 0.0
    for s in range(CM):
        if post[s] > pmax:
            pmax = post[s]
    ptot = 0.0
    for s in range(CM):
        if post[s] > live * pmax:
            ptot += post[s]
    num = np.zeros(no)
    den = np.zeros(no)
    CB = D.shape[0] if kappa > 0.0 else 1
    nbk = max(CB // (CM // M), 1)
    E = np.empty((CB, no))
    done = np.zeros(CB, np.bool_)
    for s in range(CM):
        p = post[s]
        if not p > live * pmax:
            continue
        p /= ptot
        if kappa > 0.0:
            b0, b1, a = bin0[s], bin1[s], bin_a[s]
            for b in (b0, b1):
                if not done[b]:
                    done[b] = True
                    cb = b // nbk
                    for j in range(no):
                        f = oi[j]
                        if kappa_g > 0.0:
                            g = G[cb, f] / (kappa_g + GW[cb, f])
                            E[b, j] = g + (D[b, f] - W[b, f] * g) / (kappa + W[b, f])
                        else:
                            E[b, j] = D[b, f] / (kappa + W[b, f])
            for j in range(no):
                f = oi[j]
                u = mu[s, f] + (1.0 - a) * E[b0, j] + a * E[b1, j]
                lam = lam_rows[s, f]
                num[j] += p * lam * u
                den[j] += p * lam
        else:
            for j in range(no):
                f = oi[j]
                num[j] += p * pack[s, f]
                den[j] += p * pack[s, F + f]
    r = np.empty(no)
    for j in range(no):
        r[j] = z[oi[j]] - num[j] / den[j]
    C = CM // M
    pc = np.zeros(C)
    s = 0
    for c in range(C):
        for _ in range(M):
            pc[c] += post[s]
            s += 1
    cmax = 0.0
    for c in range(C):
        if pc[c] > cmax:
            cmax = pc[c]
    csum = 0.0
    for c in range(C):
        if pc[c] > style_live * cmax:
            csum += pc[c]
        else:
            pc[c] = 0.0
    corr = np.zeros(nm)
    for c in range(C):
        if pc[c] == 0.0:
            continue
        wc = pc[c] / csum
        if nm <= no:
            A = np.empty((nm, nm))
            b = np.zeros(nm)
            for i in range(nm):
                for j in range(nm):
                    A[i, j] = prec[c, mi[i], mi[j]]
                for j in range(no):
                    b[i] += prec[c, mi[i], oi[j]] * r[j]
            x = _chol_solve(A, b)
            for i in range(nm):
                corr[i] -= wc * x[i]
        else:
            A = np.empty((no, no))
            for i in range(no):
                for j in range(no):
                    A[i, j] = cov[c, oi[i], oi[j]]
            y = _chol_solve(A, r)
            for i in range(nm):
                acc = 0.0
                for j in range(no):
                    acc += cov[c, mi[i], oi[j]] * y[j]
                corr[i] += wc * acc
    for i in range(nm):
        zf[mi[i]] += shrink * corr[i]


_old = numba.njit(nogil=True)(_correct1_old)   # (lacuna.jit's flags, no on-disk cache)


@numba.njit(nogil=True)
def _old_in_new_place(post, sup, z, zobs, zf, M, mu, bin0, bin1, bin_a, kappa, kappa_g, D, W, G, GW, lam_rows, pack,
                      cov, prec, shrink, live, style_live):  # pragma: no cover - compiled
    # the new kernel's arguments; the support ignored: all C*M states, the old way
    _old(post, z, zobs, zf, M, mu, bin0, bin1, bin_a, kappa, kappa_g, D, W, G, GW, lam_rows, pack, cov, prec, shrink,
         live, style_live)


def _with_old_kernel(kernel, module=fast):
    """A compiled copy of one of hlm.fast's steps (or condfill's) whose ``correct1`` is the old kernel."""
    g = dict(module.__dict__, correct1=_old_in_new_place)
    fn = types.FunctionType(kernel.py_func.__code__, g, kernel.py_func.__name__ + "_old_correct1")
    return numba.njit(nogil=True)(fn)


@pytest.fixture(scope="module")
def walk(data):
    from mocap.datasets import load_trial

    train = [load_trial(t) for t in ("35_01", "35_06", "35_07")]
    channels = train[0].channels
    model = train_model([m.frames for m in train], channels, n_iter=3, restarts=1, styles=2, cond_shrink=1.0)
    assert model.cond is not None
    test = load_trial("35_08").frames
    T = test.shape[0]
    obs = np.ones(test.shape, bool)
    arm = [i for i, c in enumerate(channels) if c.split(".")[0] in ("lhumerus", "lradius", "lwrist", "lhand")]
    for start in range(20, T // 2 - 60, 120):
        obs[start : start + 60, arm] = False
    legs = np.array([c.split(".")[0] in ("lfemur", "ltibia", "lfoot", "ltoes", "rfemur", "rtibia", "rfoot", "rtoes")
                     for c in channels])
    obs[T // 2 :, ~legs] = False
    return model, test, obs


def _support(model, streams) -> int:
    # the largest number of states with a non-zero posterior among the streams (the new kernel's
    # support holds these, and the states the prediction reached whose posterior underflowed to 0)
    post = model.pool.core["post"][[s.slot for s in streams]].reshape(len(streams), -1)
    return int((post != 0).sum(1).max())


def test_a_64_stream_bundle_gets_the_old_kernels_bits(walk, monkeypatch):
    model, frames, obs = walk
    new, old, plain = model.with_options(), model.with_options(), model.with_options(cond_shrink=0.0)
    assert plain.cond is None
    n, T = 64, frames.shape[0]
    offs = (np.arange(n) * 37) % T
    order = np.random.default_rng(0).permutation(n)              # handed over out of slot order
    sn = [new.stream() for _ in range(2 * n)][::2]                   # scattered pool rows
    so = [old.stream() for _ in range(2 * n)][::2]
    sp = [plain.stream() for _ in range(n)]
    ref_rows = _with_old_kernel(fast._step_rows)
    real_rows = fast._step_rows
    moved, sup = 0, []
    for t in range(160):
        rows = (offs[order] + t * 3) % T
        f, o = np.where(obs[rows], frames[rows], np.nan), obs[rows]
        a = new.step_block([sn[i] for i in order], f, o)
        monkeypatch.setattr(fast, "_step_rows", ref_rows)
        b = old.step_block([so[i] for i in order], f, o)
        monkeypatch.setattr(fast, "_step_rows", real_rows)
        c = plain.step_block([sp[i] for i in order], f, o)
        np.testing.assert_array_equal(a.frame, b.frame)
        np.testing.assert_array_equal(a.std, b.std)
        np.testing.assert_array_equal(a.style, b.style)
        np.testing.assert_array_equal(a.phase, b.phase)
        moved += int((np.abs(a.frame - c.frame) > 1e-6).any(1).sum())
        sup.append(_support(new, sn))
    # after the first frames the support is a small part of the C*M states: most were skipped
    CM = new.pool.core["post"][0].size
    assert max(sup[10:]) < CM // 4, (sup[:12], CM)
    assert np.array_equal(new.pool.core["post"], old.pool.core["post"])
    # the correction did act: many stream-frames moved by it (arm gaps and the legs-only half)
    assert moved > 160 * n // 4


def test_one_stream_gets_the_old_kernels_bits(walk, monkeypatch):
    """A lone stream (step_batch of one: ``_step_slot``), the take from three starting frames."""
    model, frames, obs = walk
    new, old = model.with_options(), model.with_options()
    ref_slot = _with_old_kernel(fast._step_slot)
    real_slot = fast._step_slot
    T = frames.shape[0]
    CM = new.pool.core["post"][0].size
    missing = 0
    for off in (0, 91, 203):
        a, b = new.stream(), old.stream()
        sup = []
        for t in range(off, off + T):
            t %= T
            f = np.where(obs[t], frames[t], np.nan)
            fa = new.step_batch([a], f[None], obs[t][None])[0]   # the daemon's lone stream: step_slot
            monkeypatch.setattr(fast, "_step_slot", ref_slot)
            fb = old.step_batch([b], f[None], obs[t][None])[0]
            monkeypatch.setattr(fast, "_step_slot", real_slot)
            np.testing.assert_array_equal(fa.frame, fb.frame)
            np.testing.assert_array_equal(fa.std, fb.std)
            assert fa.extras == fb.extras
            missing += int(not obs[t].all())
            sup.append(_support(new, [a]))
        assert max(sup[10:]) < CM // 4, (sup[:12], CM)
    assert missing > 3 * T // 2


def test_the_feature_space_path_gets_the_old_kernels_bits(walk, monkeypatch):
    """``condfill.correct_many`` (a stream's own ``step``: the compiled filter, then the
    correction on the states with post != 0), 8 streams at scattered offsets."""
    model, frames, obs = walk
    new, old = model.with_options(), model.with_options()
    ref_many = _with_old_kernel(condfill._correct_many, condfill)
    real_many = condfill._correct_many
    T = frames.shape[0]
    for off in (0, 45, 91, 150, 203, 260, 330, 401):
        a, b = new.stream(), old.stream()
        for t in range(off, off + T // 2):
            t %= T
            f = np.where(obs[t], frames[t], np.nan)
            fa = a.step(f, obs[t])
            monkeypatch.setattr(condfill, "_correct_many", ref_many)
            fb = b.step(f, obs[t])
            monkeypatch.setattr(condfill, "_correct_many", real_many)
            np.testing.assert_array_equal(fa.frame, fb.frame)
            np.testing.assert_array_equal(fa.std, fb.std)
            assert fa.extras == fb.extras
