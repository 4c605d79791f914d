"""ML-II (type-II maximum likelihood, eq. 13): the negative log marginal likelihood of the GP model
(kernel + Gaussian likelihood of eq. 2) with its analytic gradient, the data-scaled starting point and
the multi-start L-BFGS-B that ``fit_ml2`` (exact) and ``vfe.fit_vfe`` (sparse bound) share.

Inference is kept separate from prediction: ``fit_ml2`` finds hyperparameters, and
``gp.ExactPosterior`` / ``gp.SparsePosterior`` turn them and the training data into the arrays
needed to predict. Everything works on standardised regressors and targets.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy import linalg

from .backend import BACKENDS
from .kernels import GradientKernel, Kernel, WorkspaceKernel, require
from .linalg import JITTERS, LOG_2PI, NotPositiveDefiniteError, _potrf_inplace, chol_inverse, cholesky_jitter

NOISE_LOG_BOUNDS = (np.log(1e-8), np.log(10.0))


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
        self.parts = kernel.parts
        self.fused = kernel.supports(WorkspaceKernel)
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


def _nlml_jax(theta, kernel, X, y, ws):
    from .ml2_jax import nlml_and_grad_jax  # here: the optional backend stays out of a numpy process

    return nlml_and_grad_jax(theta, kernel, X, y)


def nlml_objective(backend: str = "numpy"):
    """The ML-II objective ``f(theta, kernel, X, y, workspace) -> (nlml, gradient)`` of a backend: numpy's
    ``nlml_and_grad`` (with its reusable ``NLMLWorkspace``) or JAX's (which takes no workspace)."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be 'numpy' or 'jax', got {backend!r}")
    return _nlml_jax if backend == "jax" else nlml_and_grad


#: ML-II evaluations between two progress lines of ``fit_ml2``
PROGRESS_EVERY = 10


class _Reporting:
    """An ML-II objective that also reports its progress (``fit_ml2``'s ``progress``) every
    ``PROGRESS_EVERY`` evaluations; the values and gradients are the objective's own."""

    def __init__(self, fun, progress, t0: float):
        self.fun, self.progress, self.t0 = fun, progress, t0
        self.n, self.best = 0, float("inf")

    def __call__(self, theta, kernel, X, y, ws):
        out = self.fun(theta, kernel, X, y, ws)
        self.n += 1
        if np.isfinite(out[0]):
            self.best = min(self.best, float(out[0]))
        if self.n % PROGRESS_EVERY == 0:
            self.progress(f"ML-II (eq. 13) on {X.shape[0]} rows: {self.n} evaluations, best NLML {self.best:.6g} "
                          f"nats, {time.perf_counter() - self.t0:.0f} s")
        return out


def _workspace(backend: str, kernel: Kernel, X: np.ndarray):
    return None if backend == "jax" else NLMLWorkspace(kernel, X)


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
    backend: str = "numpy",
    progress=None,
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

    backend: 'numpy' (the ``NLMLWorkspace``) or 'jax' (``ml2_jax.nlml_and_grad_jax``: the same objective
    compiled for the JAX device, for N of 10-20 thousand rows on a GPU); the optimiser is the same.

    progress: optional callable taking one line of text, called every ``PROGRESS_EVERY`` evaluations
    (rows, evaluations so far, best NLML [nats], seconds); the result does not depend on it.

    The kernel is left at the best hyperparameters; returns the best theta (kernel
    log-parameters then log sigma_y^2), its NLML and evaluation counts.
    """
    require(kernel, GradientKernel, "ML-II (ml2.fit_ml2)")
    t0 = time.perf_counter()
    base = initial_theta(kernel, X, y) if theta0 is None else np.asarray(theta0, float)
    bounds = kernel.log_bounds() + [NOISE_LOG_BOUNDS]
    if hold_redundant:
        base = np.clip(base, [b[0] for b in bounds], [b[1] for b in bounds])
        for j in kernel.redundant_indices():
            bounds[j] = (float(base[j]), float(base[j]))  # L-BFGS-B keeps a variable with equal bounds fixed
    n = X.shape[0]
    sub_evals = sub_rows = 0
    objective = nlml_objective(backend) if progress is None else _Reporting(nlml_objective(backend), progress, t0)
    if warm_start_subset and 2 <= int(warm_start_subset) < n:
        rows = np.unique(np.linspace(0, n - 1, int(warm_start_subset)).astype(int))
        Xs_, ys_ = np.ascontiguousarray(X[rows]), y[rows]
        ws_sub = _workspace(backend, kernel, Xs_)
        res_sub, _, sub_evals = multistart_lbfgsb(objective, (kernel, Xs_, ys_, ws_sub), [base], bounds,
                                                  max_iter=max_iter, stall_evals=stall_evals)
        del ws_sub
        sub_rows = rows.size
        if res_sub is not None:
            base = res_sub.x
    ws = _workspace(backend, kernel, X)
    best, history, n_evals = multistart_lbfgsb(objective, (kernel, X, y, ws), [base], bounds,
                                               n_restarts=n_restarts, seed=seed, max_iter=max_iter,
                                               agree_tol=agree_tol, stall_evals=stall_evals)
    del ws
    if best is None:
        raise NotPositiveDefiniteError("ML-II failed from every start: covariance never positive definite")
    kernel.set_theta(best.x[:-1])
    return MLIIResult(theta=best.x.copy(), nlml=float(best.fun), restarts=history,
                      seconds=time.perf_counter() - t0, n_evals=n_evals, subset_evals=sub_evals,
                      subset_rows=sub_rows)
