"""Dense linear algebra with the safeguards every GP solve here needs: a Cholesky factor with jitter
escalation (relative to the mean diagonal) and a clear error when even the largest jitter fails, the
inverse from a Cholesky factor, and LAPACK's in-place factorisation of a lower triangle."""
from __future__ import annotations

import numpy as np
from scipy import linalg

LOG_2PI = np.log(2.0 * np.pi)
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


def _potrf_inplace(KL: np.ndarray) -> tuple[np.ndarray, int]:
    """Cholesky of the lower triangle of C-ordered KL in place: KL.T is F-ordered and its upper
    triangle is KL's lower, so LAPACK factors it as U^T U with no copy; KL's lower becomes L."""
    c, info = linalg.lapack.dpotrf(KL.T, lower=0, clean=0, overwrite_a=1)
    return c, info
