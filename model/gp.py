"""GP regression: ML-II hyperparameters (eq. 13) and posteriors for prediction (eqs. 8-9).

The model (kernel + Gaussian likelihood of eq. 2) is kept separate from inference: ``fit_ml2``
finds hyperparameters; ``ExactPosterior`` and ``SparsePosterior`` turn them and the training data
into the arrays needed to predict. Everything works on standardised regressors and targets.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy import linalg

from .kernels import Kernel, Sum

LOG_2PI = np.log(2.0 * np.pi)
NOISE_LOG_BOUNDS = (np.log(1e-8), np.log(10.0))
JITTERS = (0.0, 1e-10, 1e-8, 1e-6, 1e-4, 1e-2)


class NotPositiveDefiniteError(np.linalg.LinAlgError):
    """K + sigma_y^2 I stayed non positive definite after jitter escalation."""


def cholesky_jitter(K: np.ndarray, overwrite: bool = False) -> tuple[np.ndarray, float]:
    """Lower Cholesky factor of K, adding jitter (relative to mean diag) until it succeeds.

    Returns (L, jitter added). Raises NotPositiveDefiniteError naming the largest jitter tried.
    """
    scale = float(np.mean(np.diag(K))) or 1.0
    for rel in JITTERS:
        try:
            if rel:
                Kj = K + (rel * scale) * np.eye(K.shape[0])
            else:
                Kj = K if not overwrite else K
            L = linalg.cholesky(Kj, lower=True, overwrite_a=overwrite and rel == 0.0, check_finite=False)
            if np.all(np.isfinite(L)):
                return L, rel * scale
        except linalg.LinAlgError:
            continue
    raise NotPositiveDefiniteError(
        f"covariance matrix (N={K.shape[0]}) is not positive definite even with jitter "
        f"{JITTERS[-1]:g} x mean diagonal; check for duplicated regressors or extreme hyperparameters"
    )


def chol_inverse(L: np.ndarray) -> np.ndarray:
    """(L L^T)^-1 from the lower Cholesky factor via LAPACK potri (symmetrised)."""
    inv, info = linalg.lapack.dpotri(L, lower=1)
    if info != 0:
        raise NotPositiveDefiniteError(f"potri failed (info={info})")
    inv = np.tril(inv)
    inv += np.tril(inv, -1).T
    return inv


class NLMLWorkspace:
    """Reusable buffers for ``nlml_and_grad`` on one training set (one ML-II fit).

    Holds, for the lower-triangle row blocks only, what the kernel's parts are functions of
    (``Kernel.workspace_input``: the Gram matrix G = X X^T and/or the distances r = |x - x'|, computed
    once), one buffer per part that asks for it (``Kernel.workspace_buffer``), and the N x N buffer
    that is K + sigma_y^2 I, then its Cholesky factor L, then W = K^-1 in place (LAPACK potrf/potri on
    the F-ordered view, no copies). The formulas of each part (eqs. 10-12 and their derivatives) are
    the kernel's own (``block_value``, ``block_grad_sums``, ``grads_from_sums``); this class only
    walks the blocks. Memory: (3 + buffered parts) N^2 float64 (about 0.5 GB at N=4000). A kernel
    with a part that has no block formulas falls back to ``Kernel.K_and_grads`` (``fused`` is False).
    """

    def __init__(self, kernel: Kernel, X: np.ndarray, chunk: int = 64):
        self.X = X
        n = X.shape[0]
        self.n = n
        self.parts = kernel.parts if isinstance(kernel, Sum) else [kernel]
        self.fused = all(p.workspace_ready for p in self.parts)
        if not self.fused:
            return
        self.KL = np.empty((n, n))
        self.chunk = max(8, int(chunk))
        self.blocks = [(r0, min(n, r0 + self.chunk)) for r0 in range(0, n, self.chunk)]
        inputs = {p.workspace_input for p in self.parts}
        self.G = np.empty((n, n)) if "gram" in inputs else None
        self.R = np.empty((n, n)) if "distance" in inputs else None
        self.E = [np.empty((n, n)) if p.workspace_buffer else None for p in self.parts]
        sq = np.einsum("ij,ij->i", X, X)
        for r0, r1 in self.blocks:
            g = X[r0:r1] @ X[:r1].T
            if self.R is not None:
                r = self.R[r0:r1, :r1]
                np.multiply(g, -2.0, out=r)
                r += sq[r0:r1, None]
                r += sq[None, :r1]
                np.maximum(r, 0.0, out=r)
                np.sqrt(r, out=r)
                idx = np.arange(r0, r1)
                r[idx - r0, idx] = 0.0
            if self.G is not None:
                self.G[r0:r1, :r1] = g
        self.tril_masks = {}

    def _mask(self, m: int) -> np.ndarray:
        """Lower-triangular weights of a diagonal block: 1 below, 0.5 on the diagonal, 0 above."""
        w = self.tril_masks.get(m)
        if w is None:
            w = np.tril(np.ones((m, m)), -1) + 0.5 * np.eye(m)
            self.tril_masks[m] = w
        return w

    def _block_args(self, part: Kernel, E, r0: int, r1: int):
        """(input block, buffer block) of one part for rows r0:r1 of the lower triangle."""
        base = self.R if part.workspace_input == "distance" else self.G
        return base[r0:r1, :r1], (None if E is None else E[r0:r1, :r1])

    def fill_K(self, noise: float, jitter: float = 0.0) -> None:
        """Lower triangle (row blocks) of K + (noise + jitter) I into KL: eqs. (10)-(12) summed over parts."""
        KL = self.KL
        for r0, r1 in self.blocks:
            out = KL[r0:r1, :r1]
            first = True
            for part, E in zip(self.parts, self.E):
                if part.workspace_input is None:
                    continue
                t = part.block_value(*self._block_args(part, E, r0, r1))
                if first:
                    out[...] = t
                    first = False
                else:
                    out += t
            if first:
                out[...] = 0.0
        d = noise + jitter
        for part in self.parts:
            d += part.block_diagonal()
        KL[np.diag_indices(self.n)] += d

    def grad_traces(self, alpha: np.ndarray, tr_w: float) -> list:
        """0.5 tr((K^-1 - alpha alpha^T) dK/dtheta_j) for every kernel log-parameter (not the noise).

        KL holds K^-1 in its lower triangle. Both matrices are symmetric, so the full trace is
        twice the sum over the lower triangle with the diagonal weighted 1/2; W' = K^-1 - alpha
        alpha^T is formed block by block in place and each part sums what its gradients need.
        """
        acc = [None] * len(self.parts)  # lower-triangle sums per part
        KL = self.KL
        for r0, r1 in self.blocks:
            W = KL[r0:r1, :r1]
            W -= np.outer(alpha[r0:r1], alpha[:r1])
            W[:, r0:r1] *= self._mask(r1 - r0)
            for k, (part, E) in enumerate(zip(self.parts, self.E)):
                if part.workspace_input is None:
                    continue
                sums = part.block_grad_sums(W, *self._block_args(part, E, r0, r1))
                acc[k] = sums if acc[k] is None else acc[k] + sums
        out = []
        for part, sums in zip(self.parts, acc):
            out += part.grads_from_sums(sums, tr_w)
        return out


def _potrf_inplace(KL: np.ndarray) -> tuple[np.ndarray, int]:
    """Cholesky of the lower triangle of C-ordered KL in place: KL.T is F-ordered and its upper
    triangle is KL's lower, so LAPACK factors it as U^T U with no copy; KL's lower becomes L."""
    c, info = linalg.lapack.dpotrf(KL.T, lower=0, clean=0, overwrite_a=1)
    return c, info


def nlml_and_grad(theta: np.ndarray, kernel: Kernel, X: np.ndarray, y: np.ndarray,
                  workspace: NLMLWorkspace | None = None) -> tuple[float, np.ndarray]:
    """Negative log marginal likelihood, eq. (13) negated, and its analytic gradient.

    theta = [kernel log-parameters..., log sigma_y^2] (dimensionless, standardised data).
    One Cholesky of K + sigma_y^2 I and one potri for K^-1:
    dNLML/dtheta_j = 0.5 tr((K^-1 - alpha alpha^T) dK/dtheta_j), alpha = K^-1 y.
    Pass a ``NLMLWorkspace`` built for (kernel, X) to reuse its buffers across evaluations
    (``fit_ml2`` does); without it one is built for this call.
    """
    ws = workspace if workspace is not None else NLMLWorkspace(kernel, X)
    kernel.set_theta(theta[:-1])
    noise = float(np.exp(theta[-1]))
    n = y.size
    if not ws.fused:
        return _nlml_and_grad_generic(theta, kernel, X, y, noise)
    ws.fill_K(noise)
    scale = float(np.mean(np.diag(ws.KL)))
    jitter = 0.0
    for rel in JITTERS:
        if rel:
            jitter = rel * scale
            ws.fill_K(noise, jitter)
        c, info = _potrf_inplace(ws.KL)
        if info == 0 and np.all(np.isfinite(np.diag(ws.KL))):
            break
    else:
        raise NotPositiveDefiniteError(
            f"covariance matrix (N={n}) is not positive definite even with jitter "
            f"{JITTERS[-1]:g} x mean diagonal; check for duplicated regressors or extreme hyperparameters")
    logdet_half = float(np.sum(np.log(np.diag(ws.KL))))
    alpha, info = linalg.lapack.dpotrs(c, y, lower=0)
    nlml = 0.5 * float(y @ alpha) + logdet_half + 0.5 * n * LOG_2PI
    _, info = linalg.lapack.dpotri(c, lower=0, overwrite_c=1)
    if info != 0:
        raise NotPositiveDefiniteError(f"potri failed (info={info})")
    tr_w = float(np.sum(np.diag(ws.KL))) - float(alpha @ alpha)  # tr(K^-1 - alpha alpha^T)
    g = np.empty(theta.size)
    g[:-1] = ws.grad_traces(alpha, tr_w)
    g[-1] = 0.5 * noise * tr_w
    return nlml, g


def _nlml_and_grad_generic(theta, kernel, X, y, noise):
    """Unfused path for kernels without a workspace formula: every dK/dtheta_j materialised."""
    K, grads = kernel.K_and_grads(X)
    K[np.diag_indices_from(K)] += noise
    L, _ = cholesky_jitter(K, overwrite=True)
    alpha = linalg.cho_solve((L, True), y, check_finite=False)
    n = y.size
    nlml = 0.5 * float(y @ alpha) + float(np.sum(np.log(np.diag(L)))) + 0.5 * n * LOG_2PI
    W = chol_inverse(L)
    W -= np.outer(alpha, alpha)
    g = np.empty(theta.size)
    for j, dK in enumerate(grads):
        g[j] = 0.5 * float(np.einsum("ij,ij->", W, dK))
    g[-1] = 0.5 * noise * float(np.trace(W))
    return nlml, g


def initial_theta(kernel: Kernel, X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Starting log-hyperparameters from data scales (standardised data): each kernel part's own
    ``Kernel.initial_theta`` from var(y), the median pairwise regressor distance and the regressor
    dimension, then the noise at 1 % of var(y)."""
    rng = np.random.default_rng(0)
    sub = X[rng.choice(X.shape[0], size=min(500, X.shape[0]), replace=False)]
    d2 = np.sum((sub[:, None, :] - sub[None, :, :]) ** 2, axis=-1)
    med = float(np.sqrt(np.median(d2[d2 > 0]))) if np.any(d2 > 0) else 1.0
    vy = float(np.var(y)) or 1.0
    theta = list(kernel.initial_theta(vy, med, X.shape[1]))
    theta.append(np.log(1e-2 * vy))
    return np.array(theta, dtype=float)


@dataclass
class MLIIResult:
    theta: np.ndarray
    nlml: float
    restarts: list = field(default_factory=list)  # (nlml, n_iter) per start
    seconds: float = 0.0
    n_evals: int = 0  # objective + gradient evaluations on the full data (all starts)
    subset_evals: int = 0  # evaluations spent on the warm-start subset (fit_ml2 warm_start_subset)
    subset_rows: int = 0


class _Stalled(Exception):
    """Raised inside the objective when the best value has stopped improving (see ``_StallWatch``)."""


class _StallWatch:
    """Objective wrapper: keeps the best (value, x) seen and stops the run once ``patience``
    consecutive evaluations improved the best value by less than ``tol`` in total (same units as the
    objective: nats for an NLML). L-BFGS-B near an ill-conditioned optimum can spend dozens of
    evaluations in line searches that end "ABNORMAL" without progress; this ends them early."""

    def __init__(self, fun, patience: int | None, tol: float):
        self.fun, self.patience, self.tol = fun, patience, tol
        self.best_f, self.best_x, self.n, self.since = np.inf, None, 0, 0

    def __call__(self, theta, *args):
        f, g = self.fun(theta, *args)
        self.n += 1
        if f < self.best_f - self.tol or self.best_x is None:
            self.since = 0
        else:
            self.since += 1
        if f < self.best_f:
            self.best_f, self.best_x = float(f), np.array(theta, dtype=float)
        if self.patience and self.since >= self.patience:
            raise _Stalled
        return f, g


def multistart_lbfgsb(fun, args: tuple, starts: list, bounds: list, n_restarts: int = 0, seed: int = 0,
                      max_iter: int = 200, agree_tol: float = 0.5, failure=NotPositiveDefiniteError,
                      stall_evals: int | None = None, stall_tol: float = 1e-4):
    """Minimise ``fun(theta, *args) -> (value, grad)`` by L-BFGS-B from several starts.

    The restart scheme shared by ``fit_ml2`` (exact ML-II, eq. 13) and ``vfe.fit_vfe``: first the
    fixed ``starts`` in order, then ``n_restarts`` seeded N(0, 1) log-space perturbations of
    ``starts[0]`` (clipped to ``bounds``). Once every fixed start has run, it stops as soon as two
    finished starts agree within ``agree_tol`` (same units as ``fun``, nats for an NLML). A start
    raising ``failure`` keeps its best point so far, or is recorded as (inf, 0) if it had none. With
    ``stall_evals``, a start also ends once that many consecutive evaluations improved its best value
    by less than ``stall_tol`` (its best point is kept; n_iter is then recorded as -1). Returns (best
    result, with ``x``, ``fun``, ``nfev``, or None; history of (value, n_iter) per start; total
    evaluations).
    """
    from scipy.optimize import OptimizeResult, minimize  # here: predictions never import the optimiser

    lo = np.array([b[0] for b in bounds])
    hi = np.array([b[1] for b in bounds])
    starts = [np.clip(np.asarray(s, float), lo, hi) for s in starts]
    rng = np.random.default_rng(seed)
    best, history, n_evals = None, [], 0
    n_fixed = len(starts)
    for r in range(n_fixed + int(n_restarts)):
        start = starts[r] if r < n_fixed else np.clip(starts[0] + rng.normal(0.0, 1.0, starts[0].size), lo, hi)
        watch = _StallWatch(fun, stall_evals, stall_tol)
        try:
            res = minimize(watch, start, args=args, jac=True, method="L-BFGS-B", bounds=bounds,
                           options={"maxiter": max_iter})
            if watch.best_x is not None and watch.best_f < res.fun:
                res.x, res.fun = watch.best_x, watch.best_f
        except _Stalled:
            res = OptimizeResult(x=watch.best_x, fun=watch.best_f, nfev=watch.n, nit=-1, message="stalled")
        except failure:
            n_evals += watch.n
            if watch.best_x is None:
                history.append((float("inf"), 0))
                continue
            res = OptimizeResult(x=watch.best_x, fun=watch.best_f, nfev=watch.n, nit=-1, message=str(failure))
        n_evals += int(res.nfev)
        history.append((float(res.fun), int(res.nit)))
        if best is None or res.fun < best.fun:
            best = res
        finite = sorted(h[0] for h in history if np.isfinite(h[0]))
        if r >= n_fixed - 1 and len(finite) >= 2 and finite[1] - finite[0] < agree_tol:
            break
    return best, history, n_evals


def _nlml_ws(theta, kernel, X, y, ws):
    """Objective for L-BFGS-B; looks ``nlml_and_grad`` up at call time (benchmarks may wrap it)."""
    return nlml_and_grad(theta, kernel, X, y, ws)


def redundant_scale_indices(kernel: Kernel) -> list[int]:
    """Positions in theta of the redundant parameters (the cubic parts' log scale s, eq. 11)."""
    return kernel.redundant_indices()


def default_warm_start_subset(n: int) -> int | None:
    """Warm-start subset size used by ``GPNARX`` for n ML-II rows: n // 4 from n >= 2000, else none."""
    return n // 4 if n >= 2000 else None


def fit_ml2(
    kernel: Kernel,
    X: np.ndarray,
    y: np.ndarray,
    n_restarts: int = 2,
    seed: int = 0,
    max_iter: int = 200,
    agree_tol: float = 0.5,
    theta0: np.ndarray | None = None,
    warm_start_subset: int | None = None,
    hold_redundant: bool = False,
    stall_evals: int | None = 10,
) -> MLIIResult:
    """ML-II: maximise eq. (13) by L-BFGS-B over log-hyperparameters, with seeded restarts.

    Start 0 is the data-scaled initial point (or ``theta0``); each restart perturbs it by N(0, 1)
    in log space. Restarts stop early once two starts agree within ``agree_tol`` nats (fewer
    restarts when they agree). One ``NLMLWorkspace`` is reused by every evaluation.

    warm_start_subset: if set (rows, < N), start 0 is first optimised on that many evenly strided
    rows (O(rows^3) per evaluation, e.g. N/4 costs 1/64 of a full evaluation), and the full-N
    L-BFGS-B starts from that optimum, so it needs fewer full-N evaluations; restarts then
    perturb the warm start. ``None`` (default) disables it; ``GPNARX`` uses
    ``default_warm_start_subset(N)`` (N/4 from N = 2000 rows).

    hold_redundant: hold the log scale s of each cubic part (eq. 11) at its start value. It is
    redundant: sigma_p^2 (s x.x' + b)^3 = (sigma_p^2 s^3)(x.x' + b/s)^3, so any (sigma_p^2, s, b)
    is reached with s fixed (inside the bounds), and the flat direction it adds to the NLML
    surface is removed from L-BFGS-B (on the Bouc-Wen protocol this reaches the better of the
    two optima a free s misses; see bench/bench_fit.py). ``GPNARX`` sets it together with the warm start.

    stall_evals: each L-BFGS-B run also ends once this many consecutive evaluations improved its best
    NLML by less than 1e-4 nats in total (None: only L-BFGS-B's own tests).

    The kernel is left at the best hyperparameters; returns the best theta (kernel
    log-parameters then log sigma_y^2), its NLML and evaluation counts.
    """
    t0 = time.perf_counter()
    base = initial_theta(kernel, X, y) if theta0 is None else np.asarray(theta0, float)
    bounds = kernel.log_bounds() + [NOISE_LOG_BOUNDS]
    if hold_redundant:
        base = np.clip(base, [b[0] for b in bounds], [b[1] for b in bounds])
        for j in redundant_scale_indices(kernel):
            bounds[j] = (float(base[j]), float(base[j]))  # L-BFGS-B keeps a variable with equal bounds fixed
    n = X.shape[0]
    sub_evals = sub_rows = 0
    if warm_start_subset and 2 <= int(warm_start_subset) < n:
        rows = np.unique(np.linspace(0, n - 1, int(warm_start_subset)).astype(int))
        Xs_, ys_ = np.ascontiguousarray(X[rows]), y[rows]
        ws_sub = NLMLWorkspace(kernel, Xs_)
        res_sub, _, sub_evals = multistart_lbfgsb(_nlml_ws, (kernel, Xs_, ys_, ws_sub), [base], bounds,
                                                  max_iter=max_iter, stall_evals=stall_evals)
        del ws_sub
        sub_rows = rows.size
        if res_sub is not None:
            base = res_sub.x
    ws = NLMLWorkspace(kernel, X)
    best, history, n_evals = multistart_lbfgsb(_nlml_ws, (kernel, X, y, ws), [base], bounds,
                                               n_restarts=n_restarts, seed=seed, max_iter=max_iter,
                                               agree_tol=agree_tol, stall_evals=stall_evals)
    del ws
    if best is None:
        raise NotPositiveDefiniteError("ML-II failed from every start: covariance never positive definite")
    kernel.set_theta(best.x[:-1])
    return MLIIResult(theta=best.x.copy(), nlml=float(best.fun), restarts=history,
                      seconds=time.perf_counter() - t0, n_evals=n_evals, subset_evals=sub_evals,
                      subset_rows=sub_rows)


class ExactPosterior:
    """Full GP posterior, eqs. (8)-(9), on standardised data.

    Stores alpha = (K + sigma_y^2 I)^-1 y and Linv = L^-1 (lower), so that for test points Xs:
    mean = K(Xs, X) alpha (eq. 8) and var_f = k(Xs, Xs) - |Linv K(X, Xs)|^2 (eq. 9).
    """

    kind = "exact"

    def __init__(self, kernel: Kernel, noise_var: float, X: np.ndarray, alpha: np.ndarray, Linv: np.ndarray):
        self.kernel = kernel
        self.noise_var = float(noise_var)
        self.X = X
        self.alpha = alpha
        self.Linv = np.ascontiguousarray(Linv)  # C order: Linv.T is its F-ordered (upper) view for BLAS
        self._sqX = np.einsum("ij,ij->i", X, X)
        self._LinvT32 = None
        # kernel may be a capped copy (Kernel.for_posterior): K_full = K + shift, so the mean of
        # eq. 8 is K alpha + shift * sum(alpha) while the variance uses the capped kernel
        self.mean_shift = float(kernel.cap_shift()) * float(np.sum(alpha))

    @classmethod
    def fit(cls, kernel: Kernel, noise_var: float, X: np.ndarray, y: np.ndarray,
            var_kernel: Kernel | None = None) -> "ExactPosterior":
        """alpha from ``kernel`` (eq. 8); Linv from ``var_kernel`` when given (its capped copy,
        ``Kernel.for_posterior``), which keeps eq. 9 exact when kernel carries a large constant."""
        alpha, Linv = cls._solve(kernel, noise_var, X, y)
        if var_kernel is None:
            return cls(kernel, noise_var, X, alpha, Linv)
        if var_kernel.cap_shift() > 0.0:
            Linv = cls._solve(var_kernel, noise_var, X, y)[1]
        return cls(var_kernel, noise_var, X, alpha, Linv)

    @staticmethod
    def _solve(kernel, noise_var, X, y):
        K = kernel(X)
        K[np.diag_indices_from(K)] += noise_var
        L, _ = cholesky_jitter(K, overwrite=True)
        alpha = linalg.cho_solve((L, True), y, check_finite=False)
        Linv = linalg.solve_triangular(L, np.eye(L.shape[0]), lower=True, check_finite=False)
        return alpha, np.tril(Linv)

    @property
    def n_points(self) -> int:
        return self.X.shape[0]

    def cross(self, Xs: np.ndarray) -> np.ndarray:
        """K(Xs, X) with one Gram product shared by all kernel parts."""
        return self.kernel.from_gram(Xs @ self.X.T, np.einsum("ij,ij->i", Xs, Xs), self._sqX)

    def predict(self, Xs: np.ndarray, return_var: bool = True, float32: bool = False):
        """Latent mean (eq. 8) and variance (eq. 9) at Xs (standardised units)."""
        Ks = self.cross(Xs)
        mean = Ks @ self.alpha
        mean += self.mean_shift
        if not return_var:
            return mean, None
        if float32:
            if self._LinvT32 is None:
                self._LinvT32 = np.ascontiguousarray(self.Linv, dtype=np.float32).T  # F-ordered Linv^T
            V = linalg.blas.strmm(1.0, self._LinvT32, Ks.astype(np.float32).T, side=0, lower=0, trans_a=1,
                                  overwrite_b=1).T
            red = np.einsum("ij,ij->i", V, V, dtype=np.float64)
        else:
            red = self._reduction_rows(Ks)
        var = self.kernel.diag(Xs) - red
        np.maximum(var, 1e-300, out=var)
        return mean, var

    def _reduction_rows(self, Ks: np.ndarray) -> np.ndarray:
        """|Linv k|^2 per row of Ks (eq. 9), float64; Ks is overwritten."""
        # a triangular product: dtrmm computes Linv Ks^T in place in P N^2 flops (half the dense
        # Ks @ Linv.T). Ks.T and Linv.T are F-ordered views of the C-ordered arrays, so BLAS needs no
        # copy; Linv = (Linv.T)^T, hence trans_a=1, lower=0.
        V = linalg.blas.dtrmm(1.0, self.Linv.T, np.ascontiguousarray(Ks).T, side=0, lower=0, trans_a=1,
                              overwrite_b=1).T
        return np.einsum("ij,ij->i", V, V)

    def mean_grad(self, xs: np.ndarray) -> tuple[float, float, np.ndarray]:
        """Mean, latent variance and d mean / d xs at one point xs (D,)."""
        k = self.cross(xs[None, :])[0]
        mean = float(k @ self.alpha) + self.mean_shift
        v = self.Linv @ k
        var = max(float(self.kernel.diag(xs[None, :])[0] - v @ v), 1e-300)
        grad = self.kernel.grad_x(xs, self.X).T @ self.alpha
        return mean, var, grad

    @property
    def mean_weights(self) -> np.ndarray:
        """w of the mean K(xs, X) w + mean_shift (eq. 8): alpha."""
        return self.alpha

    def mean_var_grad(self, Xs: np.ndarray, block: int = 256):
        """``mean_grad`` for many points at once: mean (eq. 8), latent variance (eq. 9) and
        d mean / d xs for every row of Xs, (rows,), (rows,), (rows, D); one kernel block per row block."""
        return _mean_var_grad(self, Xs, block)

    def arrays(self) -> dict:
        return {"X": self.X, "alpha": self.alpha, "Linv": self.Linv}

    @classmethod
    def from_arrays(cls, kernel, noise_var, arrays) -> "ExactPosterior":
        return cls(kernel, noise_var, arrays["X"], arrays["alpha"], arrays["Linv"])


def _mean_var_grad(post, Xs: np.ndarray, block: int):
    """Mean (eq. 8), latent variance (eq. 9, the posterior's own ``predict``) and the mean's gradient
    (``Kernel.grad_dot``) at every row of Xs, in row blocks sharing one Gram product per block."""
    Xs = np.ascontiguousarray(Xs, dtype=float)
    n = Xs.shape[0]
    mean, var = np.empty(n), np.empty(n)
    grad = np.empty(Xs.shape)
    X, w = post.X, post.mean_weights
    sqX = np.einsum("ij,ij->i", X, X)
    for r0 in range(0, n, block):
        r1 = min(n, r0 + block)
        xb = Xs[r0:r1]
        Ks, grad[r0:r1] = post.kernel.value_and_grad_dot(xb, X, w, xb @ X.T, np.einsum("ij,ij->i", xb, xb), sqX)
        np.dot(Ks, w, out=mean[r0:r1])
        mean[r0:r1] += post.mean_shift
        var[r0:r1] = post.kernel.diag(xb) - post._reduction_rows(Ks)
    np.maximum(var, 1e-300, out=var)
    return mean, var, grad


def local_model(post, x: np.ndarray, ny: int, Xc: np.ndarray | None = None):
    """Second-order model of the predictive mean (eq. 8) and latent variance (eq. 9) around one
    regressor x in its first ``ny`` coordinates (the lagged outputs).

    mean(x + d) ~ m0 + gm . d + d^T Hm d / 2 and var(x + d) ~ v0 + gv . d + d^T Hv d / 2 for d zero
    beyond ny. The variance is expanded as a whole, k(x, x) - |F k(x)|^2 with F the posterior's
    factor (G, or Linv for the exact posterior): q = |F k|^2 has gradient 2 (F J)^T F k and Hessian
    2 (F J)^T (F J) + 2 sum_n (F^T F k)_n d^2 k_n, J = d k / d x[:ny] (``Kernel.local_terms``).
    Costs O(M^2 ny) for one point (no per-path work). With ``Xc`` (rows x D), also eq. 8-9 exactly
    at those rows, sharing the one product with F. Returns (m0, gm, Hm, v0, gv, Hv, mean_c, var_c);
    raises NotImplementedError for kernels without ``local_terms`` and for legacy bundles.
    """
    F = getattr(post, "G", None) if post.kind == "sparse" else post.Linv
    if F is None:
        raise NotImplementedError("legacy sparse bundle (no variance factor G)")
    k, J, hess = post.kernel.local_terms(x, post.X, ny)
    kxx, gk, Hk = post.kernel.diag_local(x, ny)
    w = post.mean_weights
    nc = 0 if Xc is None else Xc.shape[0]
    B = np.empty((k.size, 1 + ny + nc))
    B[:, 0] = k
    B[:, 1: 1 + ny] = J
    if nc:
        B[:, 1 + ny:] = post.cross(Xc).T
    mw = w @ B  # k.w, J^T w, Kc w
    FB = F @ B
    Fk, FJ = FB[:, 0], FB[:, 1: 1 + ny]
    m0 = float(mw[0]) + post.mean_shift
    gm = mw[1: 1 + ny]
    Hm = hess(w)
    v0 = kxx - float(Fk @ Fk)
    gv = gk - 2.0 * (FJ.T @ Fk)
    Hv = Hk - 2.0 * (FJ.T @ FJ) - 2.0 * hess(F.T @ Fk)
    mean_c = var_c = None
    if nc:
        mean_c = mw[1 + ny:] + post.mean_shift
        FK = FB[:, 1 + ny:]
        var_c = np.maximum(post.kernel.diag(Xc) - np.einsum("ij,ij->j", FK, FK), 1e-300)
    return m0, gm, Hm, v0, gv, Hv, mean_c, var_c


def kmm_cholesky(kernel: Kernel, Z: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of K(Z, Z) + 1e-8 mean(diag) I, the inducing-point Gram matrix as every
    sparse computation jitters it (``SparsePosterior``, ``sparse_variance_reference``)."""
    Kmm = kernel(Z)
    Kmm[np.diag_indices_from(Kmm)] += 1e-8 * np.mean(np.diag(Kmm))
    return cholesky_jitter(Kmm, overwrite=True)[0]


def sparse_variance_reference(kernel: Kernel, Z: np.ndarray, X: np.ndarray, Xs: np.ndarray,
                              noise_var: float) -> np.ndarray:
    """eq. 9's sparse latent variance at Xs by an independent route, for checks (slow: one QR of an
    (N + M) x M matrix per call): k(x,x) - |Lm^-1 k|^2 + |R^-T k|^2 with Sigma = R^T R from the QR
    factorisation of [Lm^T; Knm / sigma_y] (no Gram product, no explicit inverse), Kmm jittered by
    ``kmm_cholesky`` as in ``SparsePosterior``. X: the posterior's training rows; all inputs standardised."""
    Lm = kmm_cholesky(kernel, Z)
    R = np.linalg.qr(np.vstack([Lm.T, kernel.cross(X, Z) / np.sqrt(noise_var)]), mode="r")
    Kq = kernel.cross(Xs, Z).T
    t1 = linalg.solve_triangular(Lm, Kq, lower=True, check_finite=False)
    t2 = linalg.solve_triangular(R, Kq, trans="T", lower=False, check_finite=False)
    return kernel.diag(Xs) - np.sum(t1 ** 2, 0) + np.sum(t2 ** 2, 0)


def choose_inducing(X: np.ndarray, m: int, seed: int = 0) -> np.ndarray:
    """M inducing inputs by k-means (k-means++ start, seeded) on the standardised regressors."""
    from scipy.cluster.vq import kmeans2

    if X.shape[0] <= m:
        return X.copy()
    rng = np.random.default_rng(seed)
    Z, _ = kmeans2(X, m, minit="++", seed=rng, iter=20)
    # drop any duplicate / empty centres by falling back to data points
    Z = np.unique(Z, axis=0)
    if Z.shape[0] < m:
        extra = X[rng.choice(X.shape[0], m - Z.shape[0], replace=False)]
        Z = np.vstack([Z, extra])
    return Z


class SparsePosterior:
    """Sparse (VFE / DTC predictive) posterior with M inducing inputs Z.

    With Kmm = K(Z, Z) = Lm Lm^T, Kmn = K(Z, X), Sigma = Kmm + sigma_y^-2 Kmn Knm:
    mean = K(Xs, Z) w, w = sigma_y^-2 Sigma^-1 Kmn y (eq. 8), and the latent variance (eq. 9)

        var_f = k(Xs, Xs) - k^T A k,   A = Kmm^-1 - Sigma^-1,   k = K(Z, Xs),

    evaluated as k(Xs, Xs) - |G k|^2 with the factor A = G^T G,
    G = diag(sqrt(s / (1 + s))) Q^T Lm^-1, where S = Q diag(s) Q^T is the eigendecomposition of
    sigma_y^-2 Lm^-1 Kmn Knm Lm^-T (so Kmm^-1 - Sigma^-1 = Lm^-T (I - (I + S)^-1) Lm^-1).
    Forming A itself is the same number in exact arithmetic, but when sigma_y^2 sits at ML-II's
    floor its entries reach 1/jitter while the variance is orders of magnitude smaller, so k^T A k
    carries rounding error larger than the variance and depends on the BLAS thread count. |G k|^2
    is a sum of squares of O(1) numbers, agrees with a QR evaluation of Sigma^-1
    (``sparse_variance_reference``), and costs the same one (rows x M x M) product as k^T A k
    (docs/numerics.md, safeguard 2). Bundles that store ``A`` itself still load (``legacy_A``; the
    loader warns).
    Building costs O(N M^2 + M^3).
    """

    kind = "sparse"

    def __init__(self, kernel: Kernel, noise_var: float, Z: np.ndarray, w: np.ndarray,
                 G: np.ndarray | None = None, legacy_A: np.ndarray | None = None):
        self.kernel = kernel
        self.noise_var = float(noise_var)
        self.X = Z
        self.w = w
        if (G is None) == (legacy_A is None):
            raise ValueError("SparsePosterior needs the variance factor G (or legacy_A from an old bundle)")
        self.G = None if G is None else np.asarray(G, dtype=float)
        self.legacy_A = legacy_A
        # the right-hand operand of the per-block product: G^T (C order), or the legacy A
        self._right = np.ascontiguousarray(self.G.T) if G is not None else legacy_A
        self._right32 = None
        self._sqZ = np.einsum("ij,ij->i", Z, Z)
        # as in ExactPosterior: with a capped kernel, mean = K w + shift * sum(w)
        self.mean_shift = float(kernel.cap_shift()) * float(np.sum(w))

    @property
    def A(self) -> np.ndarray:
        """Kmm^-1 - Sigma^-1 (for inspection; only legacy bundles predict with it)."""
        return self.legacy_A if self.legacy_A is not None else self.G.T @ self.G

    @classmethod
    def fit(cls, kernel: Kernel, noise_var: float, X: np.ndarray, y: np.ndarray, Z: np.ndarray,
            var_kernel: Kernel | None = None) -> "SparsePosterior":
        """w from ``kernel``; the variance factor G from ``var_kernel`` when given (see
        ``ExactPosterior.fit``). Each is computed once, from its own kernel."""
        Lm_inv, V, S = cls._whitened(kernel, noise_var, X, Z)
        LB, _ = cholesky_jitter(np.eye(Z.shape[0]) + S, overwrite=True)
        w = Lm_inv.T @ (chol_inverse(LB) @ (V @ y)) / noise_var
        if var_kernel is None:
            var_kernel = kernel
        elif var_kernel.cap_shift() > 0.0:
            Lm_inv, _, S = cls._whitened(var_kernel, noise_var, X, Z)
        s, Q = linalg.eigh(S, check_finite=False)
        s = np.maximum(s, 0.0)
        G = (np.sqrt(s / (1.0 + s))[:, None] * Q.T) @ np.tril(Lm_inv)
        return cls(var_kernel, noise_var, Z, w, G)

    @staticmethod
    def _whitened(kernel, noise_var, X, Z):
        """Lm^-1 (as LAPACK returns it), V = Lm^-1 Kmn (M x N) and S = sigma_y^-2 V V^T for one kernel."""
        m = Z.shape[0]
        Lm = kmm_cholesky(kernel, Z)
        V = linalg.solve_triangular(Lm, kernel.cross(Z, X), lower=True, check_finite=False)
        Lm_inv = linalg.solve_triangular(Lm, np.eye(m), lower=True, check_finite=False)
        return Lm_inv, V, (V @ V.T) / noise_var

    @property
    def n_points(self) -> int:
        return self.X.shape[0]

    def cross(self, Xs):
        return self.kernel.from_gram(Xs @ self.X.T, np.einsum("ij,ij->i", Xs, Xs), self._sqZ)

    ROW_BLOCK = 256  # test rows per block: the (rows x M) kernel block and its temporaries stay in cache

    def _reduction(self, Ks: np.ndarray, float32: bool) -> np.ndarray:
        """k^T A k per row of Ks (rows x M): |G k|^2, or k^T A k for a legacy bundle."""
        if float32:
            if self._right32 is None:
                self._right32 = self._right.astype(np.float32)
            K, R = Ks.astype(np.float32), self._right32
        else:
            K, R = Ks, self._right
        T = K @ R
        other = T if self.legacy_A is None else K
        return np.einsum("ij,ij->i", T, other, dtype=np.float64)

    def predict(self, Xs, return_var=True, float32=False):
        """Sparse predictive mean and latent variance at Xs (standardised units), in row blocks.

        Each block of ``ROW_BLOCK`` rows computes its kernel block K(Xs_b, Z) (one Gram product),
        mean K w and variance k(x, x) - |G k|^2, so the elementwise kernel work and the reduction
        run on cache-resident (rows x M) arrays instead of one (P x M) pass per operation.
        """
        Xs = np.asarray(Xs, dtype=float)
        P = Xs.shape[0]
        mean = np.empty(P)
        var = self.kernel.diag(Xs) if return_var else None
        sqs = np.einsum("ij,ij->i", Xs, Xs)
        step = self.ROW_BLOCK
        for r0 in range(0, P, step):
            r1 = min(P, r0 + step)
            Ks = self.kernel.from_gram(Xs[r0:r1] @ self.X.T, sqs[r0:r1], self._sqZ)
            np.dot(Ks, self.w, out=mean[r0:r1])
            mean[r0:r1] += self.mean_shift
            if return_var:
                var[r0:r1] -= self._reduction(Ks, float32)
        if not return_var:
            return mean, None
        np.maximum(var, 1e-300, out=var)
        return mean, var

    def _reduction_rows(self, Ks: np.ndarray) -> np.ndarray:
        """k^T A k per row of Ks (eq. 9), float64."""
        return self._reduction(Ks, False)

    def mean_grad(self, xs):
        k = self.cross(xs[None, :])
        mean = float(k[0] @ self.w) + self.mean_shift
        var = max(float(self.kernel.diag(xs[None, :])[0] - self._reduction(k, False)[0]), 1e-300)
        grad = self.kernel.grad_x(xs, self.X).T @ self.w
        return mean, var, grad

    @property
    def mean_weights(self) -> np.ndarray:
        """w of the mean K(xs, Z) w + mean_shift (eq. 8)."""
        return self.w

    def mean_var_grad(self, Xs, block: int = 256):
        """``mean_grad`` for many points at once (see ``ExactPosterior.mean_var_grad``)."""
        return _mean_var_grad(self, Xs, block)

    def arrays(self) -> dict:
        if self.legacy_A is not None:
            return {"Z": self.X, "w": self.w, "A": self.legacy_A}
        return {"Z": self.X, "w": self.w, "G": self.G}

    @classmethod
    def from_arrays(cls, kernel, noise_var, arrays) -> "SparsePosterior":
        if "G" in arrays:
            return cls(kernel, noise_var, arrays["Z"], arrays["w"], G=arrays["G"])
        return cls(kernel, noise_var, arrays["Z"], arrays["w"], legacy_A=arrays["A"])
