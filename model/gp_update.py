"""New training rows for an exact posterior with its hyperparameters held: a rank update of its factor.

``ExactPosterior`` (``model.gp``) stores the rows X it conditions on, alpha of eq. 8 and Linv = L^-1 of eq. 9,
where L L^T = K(X, X) + sigma_y^2 I with the posterior's kernel (the capped copy, ``Kernel.for_posterior``).

**Append** (``append_rows``, O(N^2 k + k^3) for k new rows on N): with K12 = K(X, X_new) and
K22 = K(X_new, X_new) + sigma_y^2 I, the factor of the grown matrix is block lower-triangular,

    L' = [[L, 0], [L21, L22]],   L21 = (Linv K12)^T,   L22 L22^T = K22 - L21 L21^T  (the Schur complement),

and its inverse, the stored factor, is

    Linv' = [[Linv, 0], [-L22^-1 L21 Linv, L22^-1]],

so the old N x N block is kept as it is and nothing of size N is refactored.

**The mean's weights** (``weights``, O(N^2)): alpha solves (K_full + sigma_y^2 I) alpha = y with the uncapped kernel,
which is the capped one plus the constant c = ``kernel.cap_shift()`` on every entry. With A = K + sigma_y^2 I
(A^-1 = Linv^T Linv), Sherman-Morrison gives alpha = a - b c (1^T a) / (1 + c 1^T b), a = A^-1 y, b = A^-1 1: two
products with the factor, no factorisation of the uncapped matrix (whose constant, 3e5 on the shipped bert-real,
makes it far worse conditioned than A).

**Dropping rows** (``keep_rows``): removing rows other than the last ones from a lower Cholesky factor changes
every later entry; it is done by refactoring the kept rows (O(N^3 / 3), with the same hyperparameters), the one step
of an update that is not a rank update. ``GPNARX.partial_fit`` drops rows only when the appended rows would pass the
row budget (``max_train_points``), and chooses which to keep by the model's selection rule.

**The targets** y of the stored rows are not in a bundle; ``targets`` recovers them from alpha as
y = (K_full + sigma_y^2 I) alpha (the targets the stored alpha solves for, to its own round-off).

All quantities are standardised (regressors and outputs as the posterior holds them).
"""
from __future__ import annotations

import numpy as np
from scipy import linalg

from .gp import ExactPosterior
from .linalg import cholesky_jitter, lower_times_rows


def _check_exact(post) -> None:
    if not isinstance(post, ExactPosterior):
        raise ValueError(f"a rank update needs an exact posterior, got {getattr(post, 'kind', type(post).__name__)!r}")


def targets(post: ExactPosterior) -> np.ndarray:
    """The standardised targets y (N,) of the posterior's rows: ``post.y_train`` when the posterior carries them
    (built here), else recovered from alpha as (K_full + sigma_y^2 I) alpha."""
    _check_exact(post)
    y = getattr(post, "y_train", None)
    if y is not None:
        return np.asarray(y, dtype=float)
    K = post.kernel(post.X_train)
    y = K @ post.alpha + float(post.kernel.cap_shift()) * float(np.sum(post.alpha)) + post.noise_var * post.alpha
    return y


def weights(Linv: np.ndarray, y: np.ndarray, cap_shift: float) -> np.ndarray:
    """alpha = (K + c 1 1^T + sigma_y^2 I)^-1 y from Linv = L^-1 of K + sigma_y^2 I, by Sherman-Morrison (c =
    ``cap_shift`` >= 0, standardised output variance)."""
    both = np.vstack([np.asarray(y, dtype=float), np.ones(Linv.shape[0])])  # rows y and 1
    a, b = lower_times_rows(Linv, lower_times_rows(Linv, both), transpose=True)  # A^-1 y, A^-1 1
    c = float(cap_shift)
    if c == 0.0:
        return a
    return a - b * (c * float(np.sum(a)) / (1.0 + c * float(np.sum(b))))


def _posterior(kernel, noise_var: float, X: np.ndarray, y: np.ndarray, Linv: np.ndarray) -> ExactPosterior:
    post = ExactPosterior(kernel, noise_var, X, weights(Linv, y, kernel.cap_shift()), Linv)
    post.y_train = np.asarray(y, dtype=float)
    return post


def refactor(kernel, noise_var: float, X: np.ndarray, y: np.ndarray) -> ExactPosterior:
    """The exact posterior on rows X (N, D), targets y (N,), by a full factorisation (O(N^3)) of
    K(X, X) + ``noise_var`` I with ``kernel`` (the capped posterior kernel); alpha by ``weights``."""
    K = kernel(X)
    K[np.diag_indices_from(K)] += float(noise_var)
    L, _ = cholesky_jitter(K, overwrite=True)
    Linv = np.tril(linalg.solve_triangular(L, np.eye(L.shape[0]), lower=True, check_finite=False))
    return _posterior(kernel, noise_var, np.ascontiguousarray(X, dtype=float), y, Linv)


def append_rows(post: ExactPosterior, X_new: np.ndarray, y_new: np.ndarray) -> ExactPosterior:
    """``post`` conditioned also on the rows X_new (k, D) with targets y_new (k,), hyperparameters held: the block
    rank update of the module docstring (O(N^2 k + k^3)); the new rows come last."""
    _check_exact(post)
    X_new = np.ascontiguousarray(X_new, dtype=float)
    y_new = np.asarray(y_new, dtype=float).ravel()
    if X_new.ndim != 2 or X_new.shape[1] != post.X_train.shape[1]:
        raise ValueError(f"X_new must have shape (k, {post.X_train.shape[1]}), got {X_new.shape}")
    if y_new.shape[0] != X_new.shape[0]:
        raise ValueError(f"y_new has {y_new.shape[0]} values for {X_new.shape[0]} rows")
    y_old = targets(post)
    if X_new.shape[0] == 0:
        return _posterior(post.kernel, post.noise_var, post.X_train, y_old, post.Linv)
    kernel, s2 = post.kernel, post.noise_var
    n, k = post.X_train.shape[0], X_new.shape[0]
    K12 = kernel.cross(post.X_train, X_new)  # (N, k)
    K22 = kernel(X_new)
    K22[np.diag_indices_from(K22)] += s2
    L21 = lower_times_rows(post.Linv, K12.T)  # (k, N): row j is Linv K12[:, j]
    S = K22 - L21 @ L21.T  # the Schur complement
    L22, _ = cholesky_jitter(0.5 * (S + S.T), overwrite=True)
    L22inv = np.tril(linalg.solve_triangular(L22, np.eye(k), lower=True, check_finite=False))
    # -L22^-1 L21 Linv: (Linv^T L21^T)^T is L21 Linv, row by row
    P21 = -(L22inv @ lower_times_rows(post.Linv, L21, transpose=True))
    Linv = np.zeros((n + k, n + k))
    Linv[:n, :n] = post.Linv
    Linv[n:, :n] = P21
    Linv[n:, n:] = L22inv
    return _posterior(kernel, s2, np.vstack([post.X_train, X_new]), np.concatenate([y_old, y_new]), Linv)


def keep_rows(post: ExactPosterior, rows) -> ExactPosterior:
    """``post`` on the subset ``rows`` (indices into its rows, kept in their order) alone, hyperparameters held:
    the kept rows refactored (``refactor``, O(N^3 / 3)); all rows: the posterior as it is."""
    _check_exact(post)
    n = post.X_train.shape[0]
    rows = np.asarray(rows, dtype=np.intp)
    if rows.ndim != 1 or rows.size == 0 or rows.min() < 0 or rows.max() >= n or np.unique(rows).size != rows.size:
        raise ValueError(f"rows must be distinct indices between 0 and {n - 1}, at least one")
    y = targets(post)
    rows = np.sort(rows)
    if rows.size == n:
        return _posterior(post.kernel, post.noise_var, post.X_train, y, post.Linv)
    return refactor(post.kernel, post.noise_var, post.X_train[rows], y[rows])
