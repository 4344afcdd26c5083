"""Variational EM for the Hierarchical Locomotion Model (Pan & Torresani 2009, section 3).

Hidden variables (marginalised with the mean-field Q of eq. 4): phases pi^k, style labels l^k,
latent cycles Z^c.  Parameters: parent cycle zbar, lambda_zbar (kept fixed, section 4),
lambda_s, Lambda^c, tau, d^k.  One EM iteration = ``n_var`` variational sweeps
(Q(Z) -> Q(l) -> Q(pi)) and the M-step (13)-(17) plus the missing-data update (18).

Where the paper as typeset is inconsistent with its own model we derive from eqs. (5), (6), (9)
and say so at the line:
* Q(z^{c,f}) precision: S_mm = 2 lambda_s + lambda_zbar + lambda_f^c W_cm (the paper divides by
  W_cm) and mean mu = S^{-1} (lambda_zbar zbar^f + lambda_f^c R^{c,f}) with R the *unnormalised*
  gamma-weighted sum of frames (the paper writes S instead of S^{-1} and a normalised v).
* Eq. (17): the zbar_m term is C lambda_zbar zbar_m, not zbar_m.
* Eqs. (15)-(16) are the MAP updates for Dirichlet priors with parameters 1 + eta (a Dirichlet(eta)
  with eta = 0.1 < 1 has no interior maximum); the penalty in the bound is the one these updates
  maximise: eta sum log tau + eta sum log d^k.

The bound (eq. 3 with L from eq. 5 and P from eq. 6) is computed explicitly; see ``bound``.
It never decreases across iterations (tested), because every step above is an exact coordinate
ascent on it.
"""
from __future__ import annotations

import contextlib
import contextvars
import sys
import time
import warnings
from collections.abc import Callable, Sequence

import numpy as np

from hlm import cyclic, hmm
from hlm.emissions import LOG2PI
from hlm.params import BoundWarning, FitResult, HLMParams
from lacuna.blas import single_thread_blas

__all__ = ["VariationalEM", "fit", "pi_stats", "estep_map", "HLMParams", "FitResult", "BoundWarning"]


# The E-step's per-sequence part can run elsewhere (archive/hlm_dist.py runs it on Dask
# workers): a mapper (em, Baug, plam, log_d) -> the dict ``pi_stats`` returns for all K sequences,
# in sequence order.  None = this process.
_ESTEP_MAP: contextvars.ContextVar = contextvars.ContextVar("hlm_estep_map", default=None)


@contextlib.contextmanager
def estep_map(mapper: Callable | None):
    """Run every ``VariationalEM`` E-step inside the block through ``mapper`` (see ``_ESTEP_MAP``)."""
    token = _ESTEP_MAP.set(mapper)
    try:
        yield
    finally:
        _ESTEP_MAP.reset(token)


def pi_stats(X: np.ndarray, lengths: np.ndarray, Baug: np.ndarray, plam: np.ndarray, log_d: np.ndarray) -> dict:
    """Q(pi^k) of eq. (7)/(10) for a batch of sequences and its sufficient statistics.

    X : (T, K, F) padded frames (0 on padding).  lengths : (K,).  Baug : (K, F + 1, M) the
    psi-weighted emission coefficients (last row the constant).  plam : (K, F) = psi Lambda.
    log_d : (K, J).  Returns G (T, K, M) posteriors, jumps (K, J), log_z (K,), GX (K, M, F),
    Gs (K, M) and H_pi (K,) the entropy of Q(pi^k).  Every output row k depends on sequence k
    only, so batches of sequences can be computed apart and stacked.
    """
    T, K, F = X.shape
    M = Baug.shape[2]
    valid = np.arange(T)[:, None] < lengths[None, :]
    Xk = np.ascontiguousarray(X.transpose(1, 0, 2))                           # (K, T, F)
    Xaug = np.ones((K, T, F + 1))
    Xaug[:, :, :F] = Xk
    x2 = np.einsum("ktf,kf->kt", Xk ** 2, plam)                              # (K, T)
    ek = Xaug @ Baug                                                          # (K, T, M) on BLAS
    ek -= 0.5 * x2[:, :, None]
    e = np.ascontiguousarray(ek.transpose(1, 0, 2))                           # (T, K, M)
    e[~valid] = 0.0
    log_start = np.full((K, M), -np.log(M))
    G, log_z, jumps = hmm.forward_backward(e, log_start, log_d, lengths)
    GX = np.ascontiguousarray(G.transpose(1, 2, 0)) @ Xk                      # (K, M, F)
    # entropy of Q(pi^k) = log Z_k - <log p(pi_1)> - <sum log d> - <sum e>, fixed with this Q
    H_pi = log_z + np.log(M) - (jumps * log_d).sum(1) - np.einsum("tkm,tkm->k", G, e)
    return {"G": G, "jumps": jumps, "log_z": log_z, "GX": GX, "Gs": G.sum(0), "H_pi": H_pi}


class VariationalEM:
    """One run (one seed) of the variational EM.  Call ``fit``; inspect ``bound()`` at any time.

    Parameters
    ----------
    sequences : list of (N_k, F) feature arrays; NaN marks a missing entry (filled by eq. 18).
    n_styles : C.  cycle_frames : N, the expected cycle length; M = 2 N states (section 2).
    n_jumps : J (3).  lam_s : initial lambda_s (0.1).  zbar_frac : lambda_zbar as a fraction of the
    sample precision (0.01).  eta : eta^zbar = eta^tau = eta^d (0.1).  init_noise : amplitude
    of the random perturbation of the uniform Q(l) (section 4: "small random noise").
    n_states : override M (default 2 N).  update_lam_zbar : apply eq. (12) (the paper keeps it fixed).
    """

    def __init__(self, sequences: Sequence[np.ndarray], n_styles: int, cycle_frames: int, *,
                 n_jumps: int = 3, lam_s: float = 0.1, zbar_frac: float = 0.01, eta: float = 0.1,
                 init_noise: float = 0.05, n_states: int | None = None, update_lam_zbar: bool = False,
                 seed: int = 0):
        if n_styles < 1:
            raise ValueError(f"n_styles must be >= 1 (got {n_styles})")
        if cycle_frames < 2:
            raise ValueError(f"cycle_frames must be >= 2 (got {cycle_frames})")
        seqs = [np.asarray(s, dtype=np.float64) for s in sequences]
        if not seqs:
            raise ValueError("no training sequences")
        F = seqs[0].shape[1]
        for k, s in enumerate(seqs):
            if s.ndim != 2 or s.shape[1] != F:
                raise ValueError(f"sequence {k} has shape {s.shape}, expected (n, {F})")
            if s.shape[0] < 2:
                raise ValueError(f"sequence {k} has {s.shape[0]} frames; need at least 2")
        self.C, self.F, self.J = n_styles, F, n_jumps
        self.M = int(n_states) if n_states else 2 * int(cycle_frames)
        if self.M <= 2 * n_jumps:
            raise ValueError(f"M={self.M} states is too few for J={n_jumps} (need M > 2 J)")
        self.K = len(seqs)
        self.lengths = np.array([q.shape[0] for q in seqs])
        Tmax = int(self.lengths.max())
        # padded layout (T_max, K, F): padding rows are zeros and never count (valid mask)
        self.valid = np.arange(Tmax)[:, None] < self.lengths[None, :]
        X = np.zeros((Tmax, self.K, F))
        obs = np.zeros((Tmax, self.K, F), bool)
        for k, q in enumerate(seqs):
            X[: q.shape[0], k] = q
            obs[: q.shape[0], k] = np.isfinite(q)
        self.obs = obs | ~self.valid[:, :, None]
        self.has_missing = not self.obs.all()
        allx = np.vstack(seqs)
        col_mean = np.nanmean(allx, 0) if self.has_missing else allx.mean(0)
        self.X = np.where(self.obs, X, col_mean)   # missing entries start at the feature mean
        self._all = allx
        self.eta = float(eta)
        self.update_lam_zbar = update_lam_zbar
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        self.bounds: list[float] = []
        self._init(lam_s, zbar_frac, init_noise)

    # ---- initialisation (section 4) ------------------------------------------------------------
    def _init(self, lam_s: float, zbar_frac: float, init_noise: float) -> None:
        C, M, F, K, J = self.C, self.M, self.F, self.K, self.J
        var_f = np.nanvar(self._all, 0)
        var_f = np.maximum(var_f, 1e-8 * max(var_f.max(), 1e-12))
        # zbar: the first M/2 frames of a random training sequence, linearly interpolated to M
        k0 = int(self.rng.integers(K))
        seq = self.X[: self.lengths[k0], k0]
        n = min(M // 2, seq.shape[0])
        src = np.linspace(0.0, n - 1.0, M)
        self.zbar = np.stack([np.interp(src, np.arange(n), seq[:n, f]) for f in range(F)], 1)
        self.lam = np.tile(1.0 / var_f, (C, 1))                 # sample precision per coordinate
        # eq. (14)'s precision is capped at 1e6 x the sample precision: a coordinate that is constant
        # in every take of a style (a finger channel that moves in 3 of 45 takes) has a residual of
        # ~0 there, and 1/0 would overflow the bound (hmmlearn's min_covar does the same)
        self.lam_max = 1e6 / var_f
        # "0.01 times the sample precision of all the data coordinates": one number for all f;
        # we take the precision of the average per-coordinate variance.
        self.lam_zbar = zbar_frac / float(var_f.mean())
        self.lam_s = float(lam_s)
        self.tau = np.full(C, 1.0 / C)
        self.d = np.full((K, J), 1.0 / J)
        psi = 1.0 / C + init_noise * self.rng.uniform(-1.0, 1.0, (K, C)) / C
        self.psi = psi / psi.sum(1, keepdims=True)
        self.mu = np.tile(self.zbar[None], (C, 1, 1))
        self.var = np.tile((1.0 / self.lam)[:, None, :], (1, M, 1))
        # Q(Z) starts as mu = zbar with precision lambda_f^c: no factor yet, so a dense-free stand-in
        # for the entropy term (log det S = M sum_f log lambda_f^c for that diagonal precision).
        self.logdet_S = M * np.log(self.lam)                      # (C, F)
        self.cov1 = np.zeros((C, M, F))
        self._update_pi()

    # ---- E-step pieces ------------------------------------------------------------------------
    # Nothing of shape (frames, C, M) is formed: with sum_m gamma_im = 1 every expectation of eq. (10)
    # and (11) reduces to per-sequence sufficient statistics GX_k = G_k^T X_k (M, F), Gs_k (M,).
    def _tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """lam_mu (C, M, F), lam_q (C, M) = sum_f lam (mu^2 + var), log_norm (C,) = sum_f 1/2 (log lam - log 2 pi)."""
        lam3 = self.lam[:, None, :]
        return lam3 * self.mu, (lam3 * (self.mu ** 2 + self.var)).sum(-1), 0.5 * (np.log(self.lam) - LOG2PI).sum(-1)

    def _update_pi(self) -> None:
        """Eq. (7)/(10): forward-backward with psi-weighted expected emissions
        e_k(i, m) = sum_c psi_kc <log N(x_i; z^c_m, Lambda^c^-1)>.

        The per-sequence work is ``pi_stats``; the mapper set with ``estep_map`` (default: this
        process) runs it over the sequences, e.g. on Dask workers (archive/hlm_dist.py)."""
        lam_mu, lam_q, log_norm = self._tables()
        K, M, F = self.K, self.M, self.F
        # e_k(i, m) = x_i . B_k[m] + const_k[m] - 1/2 x_i^2 . (psi_k Lambda): the (k, m) constant rides
        # along as an extra column of the product; contiguous operands keep it on BLAS
        Baug = np.empty((K, F + 1, M))
        Baug[:, :F] = np.einsum("kc,cmf->kfm", self.psi, lam_mu)
        Baug[:, F] = -0.5 * (self.psi @ lam_q) + (self.psi @ log_norm)[:, None]
        plam = self.psi @ self.lam
        log_d = np.log(self.d)
        mapper = _ESTEP_MAP.get()
        st = pi_stats(self.X, self.lengths, Baug, plam, log_d) if mapper is None else mapper(self, Baug, plam, log_d)
        self.G, self.jumps, self.log_z, self.GX, self.Gs, self.H_pi = (
            st["G"], st["jumps"], st["log_z"], st["GX"], st["Gs"], st["H_pi"])

    def _stats(self) -> tuple[np.ndarray, np.ndarray]:
        """W (C, M) = sum_k psi_kc sum_i gamma_im; R (C, M, F) = sum_k psi_kc sum_i gamma_im x_i."""
        return self.psi.T @ self.Gs, np.einsum("kc,kmf->cmf", self.psi, self.GX)

    def _update_Z(self) -> None:
        """Eq. (9) for each (c, f): Gaussian on the cycle with cyclic tridiagonal precision S^{c,f}.
        S_mm = 2 lam_s + lam_zbar + lam^c_f W_cm (derived from eq. 9; the paper's '/' is a typo),
        mu = S^{-1}(lam_zbar zbar^f + lam^c_f R^{c,f})."""
        C, M, F = self.C, self.M, self.F
        W, R = self._stats()
        a = 2.0 * self.lam_s + self.lam_zbar + self.lam[:, None, :] * W[:, :, None]   # (C, M, F)
        b = self.lam_zbar * self.zbar[None] + self.lam[:, None, :] * R
        a2 = a.transpose(1, 0, 2).reshape(M, C * F)
        fac = cyclic.factor(a2, self.lam_s)
        mu = fac.solve(b.transpose(1, 0, 2).reshape(M, C * F))
        var, cov1 = fac.marginals()
        self.mu = mu.reshape(M, C, F).transpose(1, 0, 2).copy()
        self.var = var.reshape(M, C, F).transpose(1, 0, 2).copy()
        self.cov1 = cov1.reshape(M, C, F).transpose(1, 0, 2).copy()
        self.logdet_S = fac.logdet().reshape(C, F)

    def _seq_ell(self) -> np.ndarray:
        """(K, C): sum_i sum_m gamma_im <log N(x_i; z^c_m, Lambda^c^-1)> per sequence (eq. 11's exponent)."""
        lam_mu, lam_q, log_norm = self._tables()
        x2 = (self.X ** 2).sum(0) @ self.lam.T                                   # (K, C)
        return (-0.5 * x2 + np.einsum("cmf,kmf->kc", lam_mu, self.GX) - 0.5 * self.Gs @ lam_q.T
                + self.lengths[:, None] * log_norm[None])

    def _update_l(self) -> None:
        """Eq. (8)/(11)."""
        lr = np.log(self.tau)[None] + self._seq_ell()
        lr -= lr.max(1, keepdims=True)
        p = np.exp(lr)
        self.psi = p / p.sum(1, keepdims=True)

    # ---- M-step -------------------------------------------------------------------------------
    def _m_step(self) -> None:
        C, M, F = self.C, self.M, self.F
        mu, var = self.mu, self.var
        # (13): <(z_m - z_{m+1})^2> with the cyclic lag-one covariance of Q(Z)
        nxt = np.roll(mu, -1, axis=1)
        dsq = (mu - nxt) ** 2 + var + np.roll(var, -1, axis=1) - 2.0 * self.cov1
        self.lam_s = C * M * F / float(dsq.sum())
        if self.update_lam_zbar:  # (12)
            self.lam_zbar = C * M * F / float(((mu - self.zbar[None]) ** 2 + var).sum())
        # (14)
        W, R = self._stats()
        sx2 = self.psi.T @ (self.X ** 2).sum(0)                       # (C, F)
        den = sx2 - 2.0 * (mu * R).sum(1) + (W[:, :, None] * (mu ** 2 + var)).sum(1)
        num = (self.psi * self.lengths[:, None]).sum(0)               # (C,)
        # A style no sequence uses (num ~ 0) leaves the bound independent of its Lambda (every term
        # carrying it is weighted by psi or W = 0): keep the old value instead of 0/0.
        alive = num > 1e-9 * self.lengths.sum()
        self.lam = np.where(alive[:, None], np.minimum(num[:, None] / np.maximum(den, 1e-300), self.lam_max),
                            self.lam)
        # (15), (16)
        t = self.eta + self.psi.sum(0)
        self.tau = t / t.sum()
        dd = self.eta + self.jumps
        self.d = dd / dd.sum(1, keepdims=True)
        # (17), corrected: (C lam_zbar + 4 eta) zbar_m - 2 eta (zbar_{m-1} + zbar_{m+1}) = lam_zbar sum_c mu_m^c
        a = np.full((M, F), C * self.lam_zbar + 4.0 * self.eta)
        fac = cyclic.factor(a, 2.0 * self.eta)
        self.zbar = fac.solve(self.lam_zbar * mu.sum(0))
        if self.has_missing:
            self._fill_missing()

    def _fill_missing(self) -> None:
        """Eq. (18): x_dag = (sum_c psi_c Lambda^c_dag)^{-1} sum_c psi_c sum_m gamma_m Lambda^c_dag mu^{c,m}_dag."""
        lam_mu, _, _ = self._tables()
        B = np.einsum("kc,cmf->kmf", self.psi, lam_mu)                # (K, M, F)
        num = (self.G.transpose(1, 0, 2) @ B).transpose(1, 0, 2)      # (T, K, F)
        den = (self.psi @ self.lam)[None]
        self.X = np.where(self.obs, self.X, num / den)

    # ---- the bound ----------------------------------------------------------------------------
    def bound(self) -> float:
        """The penalised variational lower bound L_Q of eq. (3).

        Included terms (all with their constants, so values compare across runs and restarts):
        per sequence k: <log tau_l> + <log p(pi_1)> (uniform, -log M) + <sum log d^k> +
        <sum_i log N(x_i; z, Lambda^-1)> + H[Q(l^k)] + H[Q(pi^k)];
        per style c and feature f: <log N(z_m; zbar_m, 1/lam_zbar)> summed over m,
        <log N(z_m; z_{m-1}, 1/lam_s)> summed cyclically over m (eq. 5), + H[Q(z^{c,f})];
        the penalty of eq. (6) (zbar smoothness) with the Dirichlet terms in the form that (15)-(16)
        maximise (eta log tau, eta log d), constants of the Dirichlet normalisers dropped.
        """
        C, M, F = self.C, self.M, self.F
        seq = (self.psi * (np.log(self.tau)[None] + self._seq_ell())).sum()
        with np.errstate(divide="ignore", invalid="ignore"):  # 0 log 0 = 0
            h_l = -np.where(self.psi > 0, self.psi * np.log(self.psi), 0.0).sum()
        seq += h_l - self.K * np.log(M) + (self.jumps * np.log(self.d)).sum() + self.H_pi.sum()
        mu, var = self.mu, self.var
        zp = C * M * F * 0.5 * (np.log(self.lam_zbar) - LOG2PI) \
            - 0.5 * self.lam_zbar * float((((mu - self.zbar[None]) ** 2) + var).sum())
        nxt = np.roll(mu, -1, axis=1)
        dsq = (mu - nxt) ** 2 + var + np.roll(var, -1, axis=1) - 2.0 * self.cov1
        zs = C * M * F * 0.5 * (np.log(self.lam_s) - LOG2PI) - 0.5 * self.lam_s * float(dsq.sum())
        hz = C * F * 0.5 * M * (1.0 + LOG2PI) - 0.5 * float(self.logdet_S.sum())
        pen = -self.eta * float(((self.zbar - np.roll(self.zbar, 1, axis=0)) ** 2).sum()) \
            + self.eta * float(np.log(self.tau).sum()) + self.eta * float(np.log(self.d).sum())
        return float(seq + zp + zs + hz + pen)

    # ---- loop ---------------------------------------------------------------------------------
    def e_step(self, n_var: int = 3) -> None:
        for _ in range(n_var):
            self._update_Z()
            self._update_l()
            self._update_pi()

    def iterate(self, n_var: int = 3) -> float:
        """One EM iteration (E-step of ``n_var`` sweeps, M-step); returns the bound after it.
        Warns (BoundWarning) if the bound drops by more than sqrt(eps) relative."""
        self.e_step(n_var)
        self._m_step()
        b = self.bound()
        if self.bounds and b < self.bounds[-1] - np.sqrt(np.finfo(float).eps) * max(1.0, abs(self.bounds[-1])):
            warnings.warn(f"HLM bound decreased at iteration {len(self.bounds) + 1}: {self.bounds[-1]:.6g} -> {b:.6g}",
                          BoundWarning, stacklevel=2)
        self.bounds.append(b)
        return b

    def converged(self, tol: float) -> bool:
        return len(self.bounds) > 1 and abs(self.bounds[-1] - self.bounds[-2]) < tol * abs(self.bounds[-2])

    def fit(self, n_iter: int = 15, n_var: int = 3, tol: float = 1e-6,
            callback: Callable[[int, float], None] | None = None) -> list[float]:
        """Run EM up to ``n_iter`` iterations in total; returns the bound after each.  Stops early
        when the relative gain is below ``tol``.  Ends with one more variational sweep so Q(Z),
        Q(l), Q(pi) match the final parameters."""
        while len(self.bounds) < n_iter and not self.converged(tol):
            b = self.iterate(n_var)
            if callback:
                callback(len(self.bounds), b)
        self.e_step(1)
        return list(self.bounds)

    def params(self) -> HLMParams:
        return HLMParams(self.zbar.copy(), self.mu.copy(), self.var.copy(), self.lam.copy(), self.tau.copy(),
                         self.d.copy(), float(self.lam_s), float(self.lam_zbar))

    def filled_sequences(self) -> list[np.ndarray]:
        return [self.X[: self.lengths[k], k].copy() for k in range(self.K)]


def fit(sequences: Sequence[np.ndarray], n_styles: int, cycle_frames: int, *, n_restarts: int = 3,
        seed: int = 0, n_iter: int = 15, n_var: int = 3, screen_iters: int | None = 2, tol: float = 1e-6,
        progress: bool = False, **options) -> FitResult:
    """Train with seeded restarts (seeds seed, seed+1, ...) and keep the one with the best bound.

    With ``screen_iters`` every restart runs that many iterations and only the best continues to
    ``n_iter`` (the restarts differ in the random parent-cycle start and Q(l) noise, whose effect
    on the bound shows within the first iterations); ``screen_iters=None`` runs every restart to
    the end and compares final bounds.
    """
    with single_thread_blas():  # E-step products are small; a second BLAS thread only spins
        return _fit(sequences, n_styles, cycle_frames, n_restarts=n_restarts, seed=seed, n_iter=n_iter,
                    n_var=n_var, screen_iters=screen_iters, tol=tol, progress=progress, **options)


def _fit(sequences, n_styles, cycle_frames, *, n_restarts, seed, n_iter, n_var, screen_iters, tol, progress,
         **options) -> FitResult:
    t0 = time.perf_counter()
    ems = []
    screen = n_iter if screen_iters is None or n_restarts == 1 else min(screen_iters, n_iter)

    def cb_for(r: int) -> Callable[[int, float], None]:
        def cb(it: int, b: float) -> None:
            if progress:
                print(f"hlm: restart {r + 1}/{n_restarts} iteration {it:2d}/{n_iter} bound {b:.8g}"
                      f"  ({time.perf_counter() - t0:.1f} s)", file=sys.stderr, flush=True)
        return cb

    for r in range(n_restarts):
        em = VariationalEM(sequences, n_styles, cycle_frames, seed=seed + r, **options)
        while len(em.bounds) < screen and not em.converged(tol):
            cb_for(r)(len(em.bounds) + 1, em.iterate(n_var))
        ems.append(em)
    finals = [em.bounds[-1] for em in ems]
    best = int(np.argmax(finals))
    em = ems[best]
    bounds = em.fit(n_iter, n_var, tol, callback=cb_for(best))
    return FitResult(em.params(), em.psi.copy(), bounds, finals, em.seed, time.perf_counter() - t0,
                     em.filled_sequences() if em.has_missing else [])
