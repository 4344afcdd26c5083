"""The online CRBM filler behind the Filler seam: clamped alternating Gibbs, batched over
streams x chains, constant time per frame.

Per frame t (section 5 of the paper and the released code, papers/NOTES.md):

1. the past n completed frames set the dynamic biases once: c* = c + x A, b* = b + x B;
2. observed features are clamped to the data; missing ones start from the previous completed
   frame plus N(0, ``init_noise``^2) noise;
3. K alternating Gibbs iterations: h ~ p(h | v, x) (eq. 2, binary samples), then the missing
   visibles are set to their Gaussian mean c* + h W^T (eq. 3); observed ones stay clamped;
4. a final mean-field step: the missing visibles become c* + p(h | v, x) W^T, with the hidden
   probabilities given the visibles of the K-th iteration (no sample: "otherwise very noisy").
   (Before 2026-12-01 the probabilities came from the K-th iteration's input, one visible update
   earlier than the released code; ``final_step="input"`` keeps that order.)

S chains run in parallel from the same history; the fill is their mean.  The per-channel std
is the spread of the visible means E[v | h] over the chains and over the second half of the
iterations (so it is informative even for S = 1).  The completed (mean) frame becomes history.

``mode="mean-field"`` is deterministic: hidden probabilities instead of samples, no init noise;
its std is the spread of E[v | h] under the factorial hidden posterior,
sqrt(sum_j W_ij^2 p_j (1 - p_j)).

Runtime knobs (not learned): ``n_gibbs`` (K), ``n_chains`` (S), ``mode``, ``init_noise``,
``final_step`` and the sampler's ``seed``, fixed when the model is made.  A step never changes
the model: the kernels take the step's knobs as an argument (``Knobs``), so one model can be
stepped from several threads at different levels at once.  The daemon degrades with
``step_batch(..., level=k)`` (K = k for that call); ``variant(...)`` gives a model with other
knobs sharing the trained arrays (``crbm.generate`` uses one).  Every fill reports
``extras["gibbs_iterations"]``.
"""
from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
from scipy.special import expit

from crbm.model import CRBM
from lacuna.filler import Fill, FillerState
from lacuna.modelfile import save_arrays
from mocap.feature_model import CoreOut, FeatureModel
from mocap.representation import Representation

MODES = ("gibbs", "mean-field")
# where the final mean-field step takes its hidden probabilities from: "last" = the visibles the
# K-th iteration left (the released code), "input" = the K-th iteration's input (this filler
# before 2026-12-01; kept by crbm-imp, crbm-ens, crbm-mf, crbm-2level, whose figures were
# measured with it)
FINAL_STEPS = ("last", "input")
_TINY32 = np.float32(1e-30)


def _logistic32(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Logistic(0, 1) noise as log(u / (1 - u)) from float32 uniforms: three times faster than
    ``rng.logistic`` and ample resolution for Bernoulli draws (u is kept off 0 so log is finite)."""
    u = rng.random(shape, dtype=np.float32)
    np.maximum(u, _TINY32, out=u)
    return np.log(u / (np.float32(1.0) - u))


class Knobs(NamedTuple):
    """One step's runtime settings, handed down to the kernels (never stored on the model by a step)."""

    n_gibbs: int       # K
    n_chains: int      # S
    mode: str          # MODES
    init_noise: float
    final_step: str    # FINAL_STEPS
    seed: int          # the sampler's seed: frame t of a stream draws from default_rng([seed, t])


def _check_iterations(k: Any) -> int:
    if isinstance(k, bool) or int(k) != k or k < 1:
        raise ValueError(f"Gibbs iterations must be an integer >= 1 (got {k!r})")
    return int(k)


def _check_chains(s: Any) -> int:
    if isinstance(s, bool) or int(s) != s or s < 1:
        raise ValueError(f"chains must be an integer >= 1 (got {s!r})")
    return int(s)


def _check_mode(mode: Any) -> str:
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES} (got {mode!r})")
    return str(mode)


def _seed_of(seed: int | None) -> int:
    return int(np.random.SeedSequence().entropy) if seed is None else int(seed)  # type: ignore[arg-type]


class CRBMModel(FeatureModel):
    """A trained CRBM (optionally with a second level, section 6) as a causal filler.

    Parameters
    ----------
    representation : the fitted feature space (Taylor's root motion, unit variance).
    crbm : the trained first level, visible width = representation.n_features.
    level2 : optional CRBM with binary visibles trained on ``crbm``'s hidden probabilities.
    n_gibbs : K, alternating Gibbs iterations per frame (30).
    n_chains : S, parallel chains averaged into the fill (1 = the paper).
    mode : "gibbs" (the paper) or "mean-field" (deterministic).
    init_noise : std of the noise added to the previous frame to start the missing visibles.
    final_step : "last" (the released code) or "input" (``FINAL_STEPS``).
    bias_rate : per-stream bias adaptation (an extension; 0, the paper's filler, turns it off).
        Every observed feature updates an exponential average, at this rate per frame, of its
        residual against the model's one-step prediction from the history (mean field, the
        frame itself unseen); a missing feature's fill is shifted by its average.  A performer
        whose foot is turned 2 degrees further out than the training population's keeps that
        offset through a gap instead of drifting to the population's mean.
    seed : seeds the filler's sampler.  The noise of stream frame t comes from a generator keyed
        by (seed, t), so a fill is reproducible and the same whether a stream runs alone, in a
        batch, offline or in the daemon (``reseed`` changes the seed for following frames).
    meta : training metadata kept for the model file.

    Degrading under load
    --------------------
    ``step_batch(..., level=k)`` steps with K = k for that call only (cost is linear in K): the
    level goes down to the kernels as an argument and the model is not touched, so concurrent
    steps at different levels do not see each other.  The daemon's scheduler degrades that way
    (``quality_levels()``: K, K/2, ..., 1); the value used is in ``Fill.extras["gibbs_iterations"]``.
    ``variant(n_gibbs=..., n_chains=..., mode=..., seed=...)`` is a new model with other knobs
    over the same trained arrays (streams of it are its own).

    ``set_iterations``, ``set_chains``, ``set_mode`` and ``reseed`` change this model's knobs for
    the following steps.  They are for offline experiments on a model nobody else is stepping;
    nothing on the serving path calls them.
    """

    method = "crbm"
    causal = True

    def __init__(self, representation: Representation, crbm: CRBM, level2: CRBM | None = None,
                 n_gibbs: int = 30, n_chains: int = 1, mode: str = "gibbs", init_noise: float = 0.01,
                 seed: int = 0, meta: dict[str, Any] | None = None, bias_rate: float = 0.0,
                 final_step: str = "last"):
        crbm._check_fitted()
        if crbm.n_visible_ != representation.n_features:
            raise ValueError(f"CRBM has {crbm.n_visible_} visible units but the representation has "
                             f"{representation.n_features} features")
        if level2 is not None and level2.n_visible_ != crbm.n_hidden:
            raise ValueError(f"second level has {level2.n_visible_} visible units, first level has {crbm.n_hidden} hidden")
        self.representation = representation
        self.crbm = crbm
        self.level2 = level2
        self.init_noise = float(init_noise)
        if not 0.0 <= float(bias_rate) < 1.0:
            raise ValueError(f"bias_rate must be in [0, 1) (got {bias_rate!r})")
        self.bias_rate = float(bias_rate)
        if final_step not in FINAL_STEPS:
            raise ValueError(f"final_step must be one of {FINAL_STEPS} (got {final_step!r})")
        self.final_step = final_step
        self.meta = dict(meta or {})
        self.set_iterations(n_gibbs)
        self.set_chains(n_chains)
        self.set_mode(mode)
        self.reseed(seed)
        F, o = crbm.n_visible_, crbm.order
        # one matmul gives both dynamic biases: x [A | B]
        self._AB = np.ascontiguousarray(np.hstack([crbm.A_, crbm.B_]))
        self._cb = np.concatenate([crbm.c_, crbm.b_])
        self._W = np.ascontiguousarray(crbm.W_)
        self._WT = np.ascontiguousarray(crbm.W_.T)
        self._F, self._o = F, o
        self._mask_cache: dict[bytes, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
        if level2 is not None:
            self._AB2 = np.ascontiguousarray(np.hstack([level2.A_, level2.B_]))
            self._cb2 = np.concatenate([level2.c_, level2.b_])

    # ---- degradation levels (the daemon's scheduler; the model's own K is left as it is) --------
    def quality_levels(self) -> list[int | None]:
        """K, K/2, K/4, ..., 1 Gibbs iterations (cost is linear in K)."""
        out: list[int | None] = [self.n_gibbs]
        v = self.n_gibbs
        while v > 1:
            v = max(1, v // 2)
            out.append(v)
        return out

    def knobs(self, level: int | None = None) -> Knobs:
        """This model's knobs, with K = ``level`` when given (checked: an integer >= 1)."""
        k = self.n_gibbs if level is None else _check_iterations(level)
        return Knobs(k, self.n_chains, self.mode, self.init_noise, self.final_step, self._seed)

    def step_batch(self, states: Sequence[FillerState], frames: np.ndarray, observed: np.ndarray,
                   level: int | None = None) -> list[Fill]:
        """``level``: K Gibbs iterations for this step only (None: the model's ``n_gibbs``).  The
        level reaches the kernels as an argument; the model is not changed."""
        if level is not None:
            level = _check_iterations(level)
        return super().step_batch(states, frames, observed, level=None if level == self.n_gibbs else level)

    def variant(self, *, n_gibbs: int | None = None, n_chains: int | None = None, mode: str | None = None,
                seed: int | None | str = "same") -> CRBMModel:
        """A model over the same trained arrays with other knobs (``seed=None``: fresh entropy;
        the default keeps this model's seed).  This model is left as it is; the new one has a
        state pool of its own."""
        new = copy.copy(self)
        new.__dict__.pop("_pool", None)           # streams of the variant are its own
        new._mask_cache = {}
        if n_gibbs is not None:
            new.n_gibbs = _check_iterations(n_gibbs)
        if n_chains is not None:
            new.n_chains = _check_chains(n_chains)
        if mode is not None:
            new.mode = _check_mode(mode)
        if seed != "same":
            new.reseed(seed)  # type: ignore[arg-type]
        return new

    # ---- knobs of this model (offline experiments only: a model being stepped elsewhere must not
    # change under it; the serving path passes ``level`` instead) ----------------------------------
    def set_iterations(self, k: int) -> None:
        """K alternating Gibbs iterations per frame for the following steps (k >= 1)."""
        self.n_gibbs = _check_iterations(k)

    def set_chains(self, s: int) -> None:
        """S parallel chains per stream for the following steps (s >= 1)."""
        self.n_chains = _check_chains(s)

    def set_mode(self, mode: str) -> None:
        self.mode = _check_mode(mode)

    def reseed(self, seed: int | None) -> None:
        self._seed = _seed_of(seed)
        self._rng = np.random.default_rng(self._seed)   # (for callers that draw from the model's generator)

    def info(self) -> dict[str, Any]:
        d = super().info()
        d.update(levels=2 if self.level2 is not None else 1, hidden=self.crbm.n_hidden, order=self.crbm.order,
                 gibbs_iterations=self.n_gibbs, chains=self.n_chains, mode=self.mode, bias_rate=self.bias_rate,
                 final_step=self.final_step)
        return d

    # ---- core -------------------------------------------------------------------------------------
    def core_init(self, n: int) -> dict[str, np.ndarray]:
        st = {"hist": np.zeros((n, self._o * self._F)), "count": np.zeros(n, dtype=np.int64),
              "bias": np.zeros((n, self._F))}     # per-stream residual averages (bias_rate)
        if self.level2 is not None:
            st["hhist"] = np.zeros((n, self.level2.order * self.crbm.n_hidden))
        return st

    def core_step(self, state: dict[str, np.ndarray], z: np.ndarray, zobs: np.ndarray,
                  rows: np.ndarray | None = None, level: int | None = None) -> CoreOut:
        """``level``: K for this step (None: the model's); everything else from ``knobs``.
        (``rows``: unused, this core has no ``core_sparse_keys``.)"""
        kn = self.knobs(level)
        hist, F = state["hist"], self._F
        first = state["count"] == 0
        if first.any():
            # no past yet: the first frame (missing features at the mean, 0) stands for it
            hist[first] = np.tile(np.where(zobs[first], z[first], 0.0), self._o)
        out = np.where(zobs, z, 0.0)
        std = np.zeros_like(out)
        need = ~zobs.all(1)
        r = self.bias_rate
        if r > 0.0:
            # the stream's residual against the one-step prediction from its history (eq. 2, 3
            # in mean field, the frame itself unseen), averaged per observed feature
            pred = self._one_step_prediction(hist)
            bias = state["bias"]
            np.copyto(bias, (1.0 - r) * bias + r * (out - pred), where=zobs & ~first[:, None])
        rows = np.flatnonzero(need)
        if rows.size:
            fill, sd = self._fill_rows(state, rows, out[rows], zobs[rows], kn)
            if r > 0.0:
                fill = fill + np.where(zobs[rows], 0.0, state["bias"][rows])
            out[rows], std[rows] = fill, sd
        if self.level2 is not None:
            self._push_level2(state, out, first)
        hist[:, F:] = hist[:, :-F].copy()
        hist[:, :F] = out
        state["count"] += 1
        info = {"gibbs_iterations": kn.n_gibbs if kn.mode == "gibbs" else 0, "chains": kn.n_chains}
        return CoreOut(out, std, [dict(info) for _ in range(z.shape[0])])

    def _one_step_prediction(self, hist: np.ndarray) -> np.ndarray:
        """(n, order F) history -> (n, F) the next frame in mean field, the frame itself unseen:
        hiddens from the previous frame and the dynamic biases (eq. 2), then E[v | h, x] (eq. 3)."""
        F = self._F
        dyn = hist @ self._AB + self._cb
        return dyn[:, :F] + expit(hist[:, :F] @ self._W + dyn[:, F:]) @ self._WT

    def _fill_rows(self, state: dict[str, np.ndarray], rows: np.ndarray, zc: np.ndarray,
                   obs: np.ndarray, kn: Knobs) -> tuple[np.ndarray, np.ndarray]:
        """zc (m, F): observed values, 0 elsewhere; obs (m, F); ``kn``: this step's knobs.  Returns
        fill and std (m, F).  Reads the trained arrays only: nothing on ``self`` is written."""
        hist = state["hist"][rows]
        m, F, H = zc.shape[0], self._F, self.crbm.n_hidden
        gibbs = kn.mode == "gibbs"
        S = kn.n_chains if gibbs else 1
        dyn = hist @ self._AB + self._cb                  # (m, F + H): c*, b*  (section 3)
        bv, bh = dyn[:, :F], dyn[:, F:]
        if self.level2 is not None:
            dyn2 = state["hhist"][rows] @ self._AB2 + self._cb2
            bv2, bh2 = dyn2[:, :H], dyn2[:, H:]
        else:
            bv2 = bh2 = None
        same = m == 1 or bool((obs == obs[0]).all())
        if same:
            # one mask for every row: only the missing columns are iterated; the observed ones
            # enter once, through the hidden input (b* + v_obs W_obs)
            mi, ob, Wm, WmT = self._mask_parts(obs[0])
            bh = bh + zc[:, ob] @ self._W[ob]
            vb = bv[:, mi]
            prev = hist[:, :F][:, mi]
            W, WT = Wm, WmT
        else:
            vb, prev, W, WT = bv, hist[:, :F], self._W, self._WT
            mi = slice(None)
        if S > 1:
            vb, bh, prev = (np.repeat(a, S, axis=0) for a in (vb, bh, prev))
            if bv2 is not None:
                bv2, bh2 = np.repeat(bv2, S, axis=0), np.repeat(bh2, S, axis=0)
        if gibbs:
            noise, L, L2 = self._draws(state["count"][rows], S, H, kn)
            v = prev + kn.init_noise * (noise[:, mi] if same else noise)
        else:
            v = prev.copy()
        if not same:
            obsS = np.repeat(obs, S, axis=0) if S > 1 else obs
            zS = np.repeat(zc, S, axis=0) if S > 1 else zc
            np.copyto(v, zS, where=obsS)
        K = kn.n_gibbs
        nr = v.shape[0]
        a = np.empty((nr, H))
        h = np.empty_like(a)
        half = K // 2
        keep = np.empty((K - half,) + v.shape)
        for it in range(K):
            np.matmul(v, W, out=a)
            a += bh                                        # eq. 2 logits: b* + v W
            if self.level2 is not None:
                # second level (section 6): its hiddens, driven by the current first-level hidden
                # state, add top-down input c2* + h2 W2^T to the first-level hidden logits
                h1 = expit(a) if it == 0 else h
                a2 = h1 @ self.level2.W_ + bh2
                h2 = (a2 > L2[it]).astype(float) if gibbs else expit(a2)
                top = h2 @ self.level2.W_.T + bv2
                a += top
            if gibbs:
                np.greater(a, L[it], out=h)               # binary samples
            else:
                expit(a, out=h)
            np.matmul(h, WT, out=v)
            v += vb                                        # eq. 3: the mean, not a sample
            if not same:
                np.copyto(v, zS, where=obsS)
            if it >= half:
                keep[it - half] = v
        # final mean-field step (section 5; the released code): the hidden probabilities given
        # the visibles the K-th iteration left (eq. 2), then the missing visibles at their mean
        # c* + p W^T (eq. 3) instead of one more sample ("otherwise very noisy")
        if kn.final_step == "last":
            np.matmul(v, W, out=a)
            a += bh
            if self.level2 is not None:
                a += top                                   # the last top-down input of level 2
        ph = expit(a)
        np.matmul(ph, WT, out=v)
        v += vb
        if gibbs:
            var = keep.var(0)
        else:
            var = (ph * (1.0 - ph)) @ (WT * WT)
        if S > 1:
            mean = v.reshape(m, S, -1).mean(1)
            # pooled spread: within-chain (second half) plus between chains
            var = var.reshape(m, S, -1).mean(1) + v.reshape(m, S, -1).var(1)
        else:
            mean = v
        sd = np.sqrt(var)
        if same:
            fill, std = zc.copy(), np.zeros_like(zc)
            fill[:, mi], std[:, mi] = mean, sd
            return fill, std
        return np.where(obs, zc, mean), np.where(obs, 0.0, sd)

    def _draws(self, counts: np.ndarray, S: int, H: int, kn: Knobs) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The frame's random numbers, per stream from a generator keyed by (seed, frame index):
        init noise (m*S, F) and logistic noise (K, m*S, H) [and (K, m*S, H2) for level 2].
        h ~ Bernoulli(logistic(a))  <=>  h = [a > L] with L ~ Logistic(0, 1), so drawing L up
        front spares a logistic function per iteration."""
        K, F = kn.n_gibbs, self._F
        H2 = self.level2.n_hidden if self.level2 is not None else 0
        noise, L, L2 = [], [], []
        for c in counts:
            g = np.random.default_rng([kn.seed, int(c)])
            noise.append(g.standard_normal((S, F)))
            L.append(_logistic32(g, (K, S, H)))
            if H2:
                L2.append(_logistic32(g, (K, S, H2)))
        return (np.concatenate(noise), np.concatenate(L, axis=1),
                np.concatenate(L2, axis=1) if H2 else None)

    def _mask_parts(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        key = np.packbits(obs).tobytes()
        got = self._mask_cache.get(key)
        if got is None:
            mi, ob = np.flatnonzero(~obs), np.flatnonzero(obs)
            Wm = np.ascontiguousarray(self._W[mi])
            got = (mi, ob, Wm, np.ascontiguousarray(Wm.T))
            if len(self._mask_cache) > 256:
                self._mask_cache.clear()
            self._mask_cache[key] = got
        return got

    def _push_level2(self, state: dict[str, np.ndarray], out: np.ndarray, first: np.ndarray) -> None:
        """The second level's history is the first level's bottom-up hidden probabilities of the
        completed frames, as in its training data."""
        H = self.crbm.n_hidden
        dyn = state["hist"] @ self.crbm.B_ + self.crbm.b_
        h1 = expit(out @ self._W + dyn)
        hh = state["hhist"]
        if first.any():
            hh[first] = np.tile(h1[first], self.level2.order)
        hh[:, H:] = hh[:, :-H].copy()
        hh[:, :H] = h1

    # ---- persistence ------------------------------------------------------------------------------
    # (crbm.persist reads the file back: it imports this module, never the other way round)
    def save(self, path: str) -> None:
        """Write the model file (lacuna.modelfile npz + JSON meta; layout in crbm/persist.py)."""
        save_arrays(path, self._file_meta(), self._file_arrays())

    def _file_meta(self) -> dict[str, Any]:
        meta: dict[str, Any] = {
            "method": self.method,
            "channels": list(self.channels),
            "representation": self.representation.to_dict(),
            "hyperparameters": {"level1": {**self.crbm.hyperparameters(), "n_epochs_done": self.crbm.n_epochs_done_}},
            "fill": {"n_gibbs": self.n_gibbs, "n_chains": self.n_chains, "mode": self.mode,
                     "init_noise": self.init_noise, "bias_rate": self.bias_rate, "final_step": self.final_step},
            "training": self.meta.get("training", {}),
        }
        if self.level2 is not None:
            meta["hyperparameters"]["level2"] = {**self.level2.hyperparameters(),
                                                 "n_epochs_done": self.level2.n_epochs_done_}
        return meta

    def _file_arrays(self) -> dict[str, np.ndarray]:
        arrays = self.crbm.get_arrays()
        if self.level2 is not None:
            arrays.update(self.level2.get_arrays("l2_"))
        return arrays
