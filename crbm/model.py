"""The conditional RBM (Taylor, Hinton & Roweis 2006): parameters, CD-1 training, Gibbs primitives.

A CRBM models frame v_t given the past n frames x_{<t} = (v_{t-1}, ..., v_{t-n}):

    E(v, h | x) = sum_i (v_i - c*_i)^2 / 2  -  sum_j b*_j h_j  -  sum_ij v_i W_ij h_j   (sigma = 1)
    c* = c + x A      (autoregressive "dynamic" visible biases, section 3)
    b* = b + x B      (past -> hidden "dynamic" hidden biases, section 3)

    p(h_j = 1 | v, x) = logistic(b*_j + sum_i v_i W_ij)                    (paper eq. 2)
    p(v_i | h, x)     = N(c*_i + sum_j W_ij h_j, 1)                          (paper eq. 3)

Binary visible units (``visible="binary"``, used by the second level of section 6 whose "data"
are the first level's hidden probabilities) replace eq. 3 by a logistic.

Arrays
------
X : (n_frames, n_visible) normalised frames (zero mean, unit variance per feature).
history : (n_cases, order * n_visible), the past frames concatenated newest first
    ``[v_{t-1}, v_{t-2}, ..., v_{t-n}]``.
W : (n_visible, n_hidden); A : (order * n_visible, n_visible); B : (order * n_visible, n_hidden);
c : (n_visible,); b : (n_hidden,).

References
----------
G. W. Taylor, G. E. Hinton, S. Roweis. Modeling Human Motion Using Binary Latent Variables.
NIPS 19, 2006.  Hyperparameters from the authors' released code (papers/NOTES.md).
"""
from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy.special import expit

from lacuna.blas import single_thread_blas

# name: (type, lower bound, upper bound or None); checked once in _check() before fit.
_PARAM_RANGES: dict[str, tuple[type, float, float | None]] = {
    "n_hidden": (int, 1, None),
    "order": (int, 1, None),
    "learning_rate": (float, 0.0, None),
    "learning_rate_ar": (float, 0.0, None),
    "weight_decay": (float, 0.0, None),
    "momentum": (float, 0.0, 1.0),
    "momentum_after": (int, 0, None),
    "batch_size": (int, 1, None),
    "n_epochs": (int, 0, None),
    "init_std": (float, 0.0, None),
    "bias_init_std": (float, 0.0, None),
    "history_noise": (float, 0.0, None),
    "average_last": (float, 0.0, 1.0),
}

_CHOICES: dict[str, tuple[str, ...]] = {"positive_hidden": ("sample", "prob"), "visible": ("gaussian", "binary"),
                                        "batches": ("reshuffle", "fixed"), "dtype": ("float64", "float32")}


class CRBM:
    """Conditional RBM with Gaussian (sigma = 1) or binary visible units and binary hidden units.

    Parameters
    ----------
    n_hidden : number of binary hidden units (paper: 150-200).
    order : n, the number of past frames feeding both directed connection sets (paper: 3).
    learning_rate : for W, B and both biases (released code: 1e-3).
    learning_rate_ar : for the autoregressive weights A (released code: 1e-5).
    weight_decay : L2 decay on W, A, B (2e-4).
    momentum : applied after ``momentum_after`` epochs (0.9 after 5).
    batch_size : mini-batch size (100).
    n_epochs : epochs run by ``fit`` (the released demo: 2000).
    init_std : weights start from N(0, init_std^2) (0.01).
    bias_init_std : the visible and hidden biases start from N(0, bias_init_std^2) (the released
        code: 0.01, as the weights; 0 = zeros).
    batches : "fixed" = the released code: the modelled frames are shuffled once, cut into
        ``n_cases // batch_size`` mini-batches of exactly ``batch_size`` (the remainder is not
        used; fewer than ``batch_size`` cases make one mini-batch) and the same mini-batches are
        visited in the same order every epoch (section 3: chunks "randomly assigned to different
        mini-batches"); "reshuffle" = a new permutation every epoch, the last mini-batch smaller.
    positive_hidden : "sample" = the paper's section 3 (binary hidden states in the data term of
        W and B), "prob" = the released code (hidden probabilities there).
    history_noise : std of Gaussian noise added to the past frames that condition each training
        case (0 = the paper's text; 1 = Taylor's released code, ``mixgaussiancrbm.m``).  Makes the dynamic biases robust
        to imperfect history, which is what a filler feeds back during a gap.
    visible : "gaussian" (joint angles) or "binary" (a second level on hidden activities).
    average_last : ``fit`` returns the average of the parameters over this final fraction of
        its epochs (0 = the paper: the last iterate).  Averaging the iterates of momentum SGD
        removes much of the epoch-to-epoch jitter that a free-running fill amplifies.
    dtype : the arithmetic of training: "float64", or "float32" as the released code trains
        (``train.m``: ``batchdata = single(Z)``; ``mixgaussiancrbm.m``: every parameter, increment
        and statistic ``single``, the draws double and cast on use).  ``fit`` returns float64
        parameters either way (``crbmfill.m``: ``W = double(M.vishid)``).
    random_state : int seed; training is reproducible given it.
    verbose : print reconstruction error per epoch on stderr (or call ``progress``).

    Attributes (set by fit / partial_fit)
    -------------------------------------
    W_, A_, B_, c_, b_ : parameters, shapes above.
    n_visible_ : int; n_epochs_done_ : int; recon_errors_ : list of per-epoch mean squared
    reconstruction error per frame (summed over units).
    """

    def __init__(self, n_hidden: int = 150, order: int = 3, learning_rate: float = 1e-3,
                 learning_rate_ar: float = 1e-5, weight_decay: float = 2e-4, momentum: float = 0.9,
                 momentum_after: int = 5, batch_size: int = 100, n_epochs: int = 2000,
                 init_std: float = 0.01, bias_init_std: float = 0.0, batches: str = "reshuffle",
                 positive_hidden: str = "sample", history_noise: float = 0.0, visible: str = "gaussian",
                 average_last: float = 0.0, dtype: str = "float64", random_state: int | None = 0, verbose: bool = False,
                 progress: Callable[[int, float], None] | None = None):
        self.n_hidden = n_hidden
        self.order = order
        self.learning_rate = learning_rate
        self.learning_rate_ar = learning_rate_ar
        self.weight_decay = weight_decay
        self.momentum = momentum
        self.momentum_after = momentum_after
        self.batch_size = batch_size
        self.n_epochs = n_epochs
        self.init_std = init_std
        self.bias_init_std = bias_init_std
        self.batches = batches
        self.positive_hidden = positive_hidden
        self.history_noise = history_noise
        self.visible = visible
        self.average_last = average_last
        self.dtype = dtype
        self.random_state = random_state
        self.verbose = verbose
        self.progress = progress

    # ---- checks -------------------------------------------------------------------------------
    def hyperparameters(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in (*_PARAM_RANGES, *_CHOICES, "random_state")}

    def _check(self) -> None:
        for name, (typ, lo, hi) in _PARAM_RANGES.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or (typ is int and int(v) != v):
                raise ValueError(f"{name} must be {'an integer' if typ is int else 'a number'} (got {v!r})")
            if v < lo or (hi is not None and v > hi) or (typ is int and name in ("n_hidden", "order", "batch_size") and v < 1):
                raise ValueError(f"{name} must be in [{lo}, {hi if hi is not None else 'inf'}] (got {v!r})")
        for name, allowed in _CHOICES.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(map(repr, allowed))} (got {getattr(self, name)!r})")

    def _check_fitted(self) -> None:
        if not hasattr(self, "W_"):
            raise ValueError("this CRBM is not trained yet; call fit or partial_fit first")

    # ---- data plumbing ------------------------------------------------------------------------
    def _stack(self, sequences: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Concatenate sequences; return X (N, V) and the indices of frames that have ``order``
        past frames inside their own sequence (each is one training chunk, never crossing a
        sequence boundary; the first n frames of a sequence are not modelled, section 3)."""
        seqs = [np.asarray(s, dtype=np.float64) for s in sequences]
        if not seqs:
            raise ValueError("no training sequences")
        widths = {s.shape[1] if s.ndim == 2 else -1 for s in seqs}
        if len(widths) != 1 or -1 in widths:
            raise ValueError(f"training sequences must be 2-D with one common width (got shapes {[s.shape for s in seqs][:5]})")
        if hasattr(self, "n_visible_") and seqs[0].shape[1] != self.n_visible_:
            raise ValueError(f"training frames have {seqs[0].shape[1]} features; this CRBM has {self.n_visible_}")
        X = np.vstack(seqs)
        if not np.all(np.isfinite(X)):
            raise ValueError("training frames contain NaN or infinity")
        idx, start = [], 0
        for s in seqs:
            if s.shape[0] > self.order:
                idx.append(np.arange(start + self.order, start + s.shape[0]))
            start += s.shape[0]
        if not idx:
            raise ValueError(f"every training sequence is shorter than order + 1 = {self.order + 1} frames")
        return X, np.concatenate(idx)

    def history_at(self, X: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """(len(idx), order * V): the past frames of X[idx], newest first, gathered by index."""
        return np.concatenate([X[idx - q] for q in range(1, self.order + 1)], axis=1)

    # ---- initialisation -----------------------------------------------------------------------
    def _init(self, n_visible: int) -> None:
        self._check()
        self._rng = np.random.default_rng(self.random_state)
        r, s, nV, nH, n = self._rng, self.init_std, n_visible, self.n_hidden, self.order
        self.n_visible_ = nV
        self.W_ = r.normal(0.0, s, (nV, nH))
        self.A_ = r.normal(0.0, s, (n * nV, nV))
        self.B_ = r.normal(0.0, s, (n * nV, nH))
        sb = self.bias_init_std
        self.c_ = r.normal(0.0, sb, nV) if sb > 0 else np.zeros(nV)
        self.b_ = r.normal(0.0, sb, nH) if sb > 0 else np.zeros(nH)
        self._as_dtype()      # released: single(0.01*randn(...)), drawn in double, then cast
        self._inc = {k: np.zeros_like(getattr(self, k)) for k in ("W_", "A_", "B_", "c_", "b_")}
        self.n_epochs_done_ = 0
        self.recon_errors_: list[float] = []
        self._batches: list[np.ndarray] | None = None   # "fixed": cut on the first epoch

    def _as_dtype(self) -> None:
        """Parameters (and increments, once they exist) in the training arithmetic ``dtype``."""
        dt = np.dtype(self.dtype)
        for k in ("W_", "A_", "B_", "c_", "b_"):
            setattr(self, k, getattr(self, k).astype(dt, copy=False))
        for k, v in getattr(self, "_inc", {}).items():
            self._inc[k] = v.astype(dt, copy=False)

    def _epoch_batches(self, idx: np.ndarray) -> list[np.ndarray]:
        """The epoch's mini-batches of case indices (never crossing a sequence: ``idx`` holds only
        frames with ``order`` past frames in their own sequence, see ``_stack``)."""
        B = self.batch_size
        if self.batches == "reshuffle":
            order = self._rng.permutation(idx)
            return [order[s : s + B] for s in range(0, len(order), B)]
        if self._batches is None or not np.array_equal(self._batch_cases, idx):
            nb = max(1, len(idx) // B)     # fewer than B cases: one smaller mini-batch of all
            order = self._rng.permutation(idx)
            self._batches = [order[b * B : (b + 1) * B] for b in range(nb)]
            self._batch_cases = idx.copy()
        return self._batches

    # ---- Gibbs primitives ---------------------------------------------------------------------
    def dynamic_biases(self, history: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """history (m, order*V) -> (c* (m, V), b* (m, H)); section 3's dynamically changing biases."""
        self._check_fitted()
        return self.c_ + history @ self.A_, self.b_ + history @ self.B_

    def _mean_hiddens(self, v: np.ndarray, bh: np.ndarray) -> np.ndarray:
        """p(h = 1 | v, x) = logistic(b* + v W), eq. 2.  (m, H)"""
        return expit(v @ self.W_ + bh)

    def _sample_hiddens(self, v: np.ndarray, bh: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        p = self._mean_hiddens(v, bh)
        return (rng.random(p.shape) < p).astype(v.dtype)

    def _mean_visibles(self, h: np.ndarray, bv: np.ndarray) -> np.ndarray:
        """E[v | h, x] = c* + h W^T (eq. 3, sigma = 1); logistic of it for binary visibles.  (m, V)"""
        a = h @ self.W_.T + bv
        return expit(a) if self.visible == "binary" else a

    def free_energy(self, v: np.ndarray, history: np.ndarray) -> np.ndarray:
        """F(v | x) = sum_i (v_i - c*_i)^2 / 2 - sum_j log(1 + exp(b*_j + v W_j)), (m,).
        log(1 + e^a) = logaddexp(0, a), stable for large |a|."""
        bv, bh = self.dynamic_biases(history)
        vis = 0.5 * ((v - bv) ** 2).sum(1) if self.visible == "gaussian" else -(v * bv).sum(1)
        return vis - np.logaddexp(0.0, v @ self.W_ + bh).sum(1)

    def gibbs(self, v: np.ndarray, history: np.ndarray, rng: np.random.Generator | None = None,
              clamp: np.ndarray | None = None) -> np.ndarray:
        """One alternating Gibbs step as in the released code: h ~ p(h | v, x), then v set to its
        expected value E[v | h, x]; entries where ``clamp`` (m, V) is True keep their input value.
        v: (m, V) -> (m, V)."""
        self._check_fitted()
        rng = rng if rng is not None else self._rng
        bv, bh = self.dynamic_biases(history)
        out = self._mean_visibles(self._sample_hiddens(v, bh, rng), bv)
        return np.where(clamp, v, out) if clamp is not None else out

    def hidden_probabilities(self, sequences: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Per sequence, p(h_t | v_t, v_{<t}) for t >= order: (n_i - order, H) each.  The data for
        the second level (section 6)."""
        self._check_fitted()
        out = []
        for s in sequences:
            X, idx = self._stack([s])
            _, bh = self.dynamic_biases(self.history_at(X, idx))
            out.append(self._mean_hiddens(X[idx], bh))
        return out

    # ---- learning -----------------------------------------------------------------------------
    def _cd1(self, v: np.ndarray, hist: np.ndarray, momentum: float) -> float:
        """One CD-1 update on a mini-batch with the paper's approximations (section 3):
        expected visible values in the reconstruction, sampled binary hiddens to drive it,
        hidden probabilities in the negative statistics.  Returns the summed squared error."""
        rng, m = self._rng, v.shape[0]
        if self.history_noise > 0:
            # the released code: past = data(t - q) + randn, for the dynamic biases and for the
            # A and B statistics alike
            hist = hist + (self.history_noise * rng.standard_normal(hist.shape)).astype(hist.dtype, copy=False)
        bv, bh = self.c_ + hist @ self.A_, self.b_ + hist @ self.B_
        ph = expit(v @ self.W_ + bh)                                   # eq. 2
        hs = (rng.random(ph.shape) < ph).astype(v.dtype)
        hpos = hs if self.positive_hidden == "sample" else ph
        vneg = self._mean_visibles(hs, bv)                            # eq. 3, mean not sample
        phn = expit(vneg @ self.W_ + bh)
        dv, dh = v - vneg, hpos - phn
        grads = {
            "W_": (v.T @ hpos - vneg.T @ phn) / m,                      # eq. 4: <v h>data - <v h>recon
            "B_": hist.T @ dh / m,                                      # eq. 6: x (<h>data - <h>recon)
            "A_": hist.T @ dv / m,                                      # eq. 7: x (<v>data - <v>recon)
            "c_": dv.mean(0),
            "b_": dh.mean(0),                                           # eq. 5
        }
        for k, g in grads.items():
            p = getattr(self, k)
            lr = self.learning_rate_ar if k == "A_" else self.learning_rate
            if k in ("W_", "A_", "B_"):
                g = g - self.weight_decay * p
            inc = self._inc[k]
            inc *= momentum
            inc += lr * g
            p += inc
        return float((dv ** 2).sum())

    def partial_fit(self, sequences: Sequence[np.ndarray]) -> CRBM:
        """One epoch of CD-1 over ``sequences`` (list of (n_i, V)); initialises on the first call."""
        X, idx = self._stack(sequences)
        if not hasattr(self, "W_"):
            self._init(X.shape[1])
        if self.W_.dtype != np.dtype(self.dtype):
            self._as_dtype()
        X = X.astype(self.dtype, copy=False)
        t0 = time.perf_counter()
        batches = self._epoch_batches(idx)
        # released code: no momentum in epochs 1-5, 0.9 from the 6th on
        mom = self.momentum if self.n_epochs_done_ >= self.momentum_after else 0.0
        err = 0.0
        with single_thread_blas():
            for bi in batches:
                err += self._cd1(X[bi], self.history_at(X, bi), mom)
        self.n_epochs_done_ += 1
        self.recon_errors_.append(err / sum(map(len, batches)))
        if not np.all(np.isfinite(self.W_)):
            raise FloatingPointError(f"CRBM training diverged at epoch {self.n_epochs_done_} (weights not finite)")
        if self.progress is not None:
            self.progress(self.n_epochs_done_, self.recon_errors_[-1])
        elif self.verbose:
            print(f"crbm epoch {self.n_epochs_done_}: reconstruction error {self.recon_errors_[-1]:.4f} "
                  f"per frame ({time.perf_counter() - t0:.3f} s)", file=sys.stderr)
        return self

    def fit(self, sequences: Sequence[np.ndarray], n_epochs: int | None = None) -> CRBM:
        """Train from scratch for ``n_epochs`` (default ``self.n_epochs``) epochs."""
        self._check()
        for k in ("W_", "A_", "B_", "c_", "b_", "n_visible_"):
            self.__dict__.pop(k, None)
        seqs = [np.asarray(s, dtype=np.float64) for s in sequences]
        self._stack(seqs)  # validate before initialising
        self._init(seqs[0].shape[1])
        E = self.n_epochs if n_epochs is None else n_epochs
        start = E - int(round(self.average_last * E)) if self.average_last > 0 else E
        keys = ("W_", "A_", "B_", "c_", "b_")
        acc = {k: np.zeros_like(getattr(self, k)) for k in keys}
        with single_thread_blas():
            for e in range(E):
                self.partial_fit(seqs)
                if e >= start:
                    for k in keys:
                        acc[k] += getattr(self, k)
        if E > start:
            for k in keys:
                setattr(self, k, acc[k] / (E - start))
        for k in keys:
            setattr(self, k, getattr(self, k).astype(np.float64))
        return self

    def reconstruction_error(self, sequences: Sequence[np.ndarray], rng: np.random.Generator | None = None) -> float:
        """Mean over modelled frames of the summed squared CD-1 reconstruction error."""
        self._check_fitted()
        X, idx = self._stack(sequences)
        rng = rng if rng is not None else np.random.default_rng(0)
        out = self.gibbs(X[idx], self.history_at(X, idx), rng)
        return float(((X[idx] - out) ** 2).sum() / len(idx))

    # ---- persistence --------------------------------------------------------------------------
    def get_arrays(self, prefix: str = "") -> dict[str, np.ndarray]:
        self._check_fitted()
        return {prefix + k.rstrip("_"): getattr(self, k) for k in ("W_", "A_", "B_", "c_", "b_")}

    @classmethod
    def from_arrays(cls, hyper: dict[str, Any], arrays: dict[str, np.ndarray], prefix: str = "") -> CRBM:
        """Rebuild a trained CRBM; raises ValueError naming any array of the wrong shape."""
        m = cls(**{k: v for k, v in hyper.items() if k in _PARAM_RANGES or k in _CHOICES or k == "random_state"})
        m._check()
        W = np.asarray(arrays[prefix + "W"], dtype=np.float64)
        if W.ndim != 2 or W.shape[1] != m.n_hidden:
            raise ValueError(f"array {prefix}W has shape {W.shape}, expected (n_visible, {m.n_hidden})")
        nV, nH, n = W.shape[0], m.n_hidden, m.order
        for k, shape in (("A", (n * nV, nV)), ("B", (n * nV, nH)), ("c", (nV,)), ("b", (nH,))):
            a = np.asarray(arrays[prefix + k], dtype=np.float64)
            if a.shape != shape:
                raise ValueError(f"array {prefix}{k} has shape {a.shape}, expected {shape}")
            setattr(m, k + "_", a)
        m.W_, m.n_visible_ = W, nV
        m._rng = np.random.default_rng(m.random_state)
        m._inc = {k: np.zeros_like(getattr(m, k)) for k in ("W_", "A_", "B_", "c_", "b_")}
        m._batches = None
        m.n_epochs_done_ = int(hyper.get("n_epochs_done", 0))
        m.recon_errors_ = []
        return m
