"""Dense linear algebra with the safeguards every GP solve here needs: a Cholesky factor with jitter
escalation (relative to the mean diagonal) and a clear error when even the largest jitter fails, the
inverse from a Cholesky factor, and LAPACK's in-place factorisation of a lower triangle.

Also the BLAS plumbing of the free runs: products with a lower-triangular factor by dtrmm without the GIL
(``lower_times_rows``, ``lower_times_rows_and_back``), split over one helper thread where the process may use
two CPUs (``two_cpus``) and the BLAS runs on one thread (``blas_threads``)."""
from __future__ import annotations

import os

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


def _fortran_dtrmm():
    """LAPACK's dtrmm as scipy's Cython BLAS exports it, called through ctypes (which releases the GIL
    for the call), or None where that export is missing. ``scipy.linalg.blas.dtrmm`` holds the GIL for
    the whole product, so a free run's worker thread (``freerun.simulate_linear``) would stall the
    Python loop running beside it; the arithmetic is the same routine's."""
    try:
        import ctypes

        from scipy.linalg import cython_blas

        cap = cython_blas.__pyx_capi__["dtrmm"]
        api = ctypes.pythonapi
        api.PyCapsule_GetName.restype = ctypes.c_char_p
        api.PyCapsule_GetName.argtypes = [ctypes.py_object]
        api.PyCapsule_GetPointer.restype = ctypes.c_void_p
        api.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
        ptr = api.PyCapsule_GetPointer(cap, api.PyCapsule_GetName(cap))
        c, i = ctypes.c_char_p, ctypes.POINTER(ctypes.c_int)
        d, v = ctypes.POINTER(ctypes.c_double), ctypes.c_void_p
        return ctypes.CFUNCTYPE(None, c, c, c, c, i, i, d, v, i, v, i)(ptr)
    except Exception:  # pragma: no cover - a scipy without the export: scipy.linalg.blas below
        return None


_DTRMM = _fortran_dtrmm()


_HELPER = []  # one lazily started helper thread for ``lower_times_rows(..., split=True)``


def two_cpus() -> bool:
    """Whether this process may run on two or more CPUs (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0)) >= 2
    except AttributeError:  # pragma: no cover - no sched_getaffinity (macOS, Windows)
        return (os.cpu_count() or 1) >= 2


_BLAS_LIBS = []  # threadpoolctl's controllers of the loaded BLAS libraries (numpy's and scipy's; found once)


def blas_threads() -> int:
    """The most threads any loaded BLAS (numpy's, scipy's) uses now; 1 where threadpoolctl finds none. The
    libraries are looked up once; each call asks their current thread count (so
    ``threadpoolctl.threadpool_limits`` blocks take effect)."""
    if not _BLAS_LIBS:
        try:
            from threadpoolctl import ThreadpoolController

            _BLAS_LIBS.append(ThreadpoolController().select(user_api="blas").lib_controllers)
        except Exception:  # pragma: no cover - threadpoolctl comes with scikit-learn
            _BLAS_LIBS.append([])
    counts = [int(c.num_threads) for c in _BLAS_LIBS[0]]
    return max(counts) if counts else 1


def lower_times_rows(L: np.ndarray, Ks: np.ndarray, split: bool = False, transpose: bool = False) -> np.ndarray:
    """(L Ks^T)^T for a lower-triangular C-ordered L (N, N) and rows Ks (rows, N), float64: row j is
    L k_j (``transpose``: L^T k_j). BLAS dtrmm (P N^2 flops, half a dense product) on a C-ordered copy of
    Ks, without the GIL where scipy exports it (``_fortran_dtrmm``), so other Python threads keep running.
    ``split``: where the process may use two CPUs and the BLAS runs on one thread, the first half of the rows
    on a helper thread while this thread does the second (with a multi-threaded BLAS, one call: two calls at
    once on its shared thread pool run several times slower than either alone)."""
    L = np.ascontiguousarray(L, dtype=np.float64)
    B = np.array(Ks, dtype=np.float64, order="C", copy=True)  # C (rows, N) = Fortran (N, rows): B^T
    rows, N = B.shape
    if _DTRMM is None or rows == 0 or N == 0:
        return linalg.blas.dtrmm(1.0, L.T, B.T, side=0, lower=0, trans_a=0 if transpose else 1, overwrite_b=1).T
    if split and rows >= 8 and _two_threads():
        h = rows // 2
        first = _helper().submit(_dtrmm_rows, L, B[:h], transpose)
        _dtrmm_rows(L, B[h:], transpose)
        first.result()
    else:
        _dtrmm_rows(L, B, transpose)
    return B


def lower_times_rows_and_back(L: np.ndarray, Ks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``lower_times_rows(L, Ks)`` and L^T (L k_0) for its first row k_0, float64 (the local model's F [k | ...]
    and F^T F k). A product with one vector streams all of L for a few flops, so where the process may use
    two CPUs and the BLAS runs on one thread, the helper thread takes row 0, then L^T of it, then a share of
    the other rows that evens the two threads' work (one row alone costs about as much as a dozen in one
    call), while this thread does the rest; otherwise one call, then the second product."""
    L = np.ascontiguousarray(L, dtype=np.float64)
    B = np.array(Ks, dtype=np.float64, order="C", copy=True)
    rows, N = B.shape
    back = np.empty((1, N))
    if _DTRMM is None or rows == 0 or N == 0:
        B = lower_times_rows(L, B)
        return B, lower_times_rows(L, B[:1], transpose=True)[0]
    if rows < 8 or not _two_threads():
        _dtrmm_rows(L, B)
        back[0] = B[0]
        _dtrmm_rows(L, back, transpose=True)
        return B, back[0]
    extra = max(0, (rows - 13) // 2)  # the helper's share of the other rows: 8 of 28

    def first():
        _dtrmm_rows(L, B[:1])
        back[0] = B[0]
        _dtrmm_rows(L, back, transpose=True)
        if extra:
            _dtrmm_rows(L, B[1: 1 + extra])

    job = _helper().submit(first)
    _dtrmm_rows(L, B[1 + extra:])
    job.result()
    return B, back[0]


def _two_threads() -> bool:
    """Whether a product may be split over this thread and the helper: two CPUs, one BLAS thread (with more,
    two calls at once on the BLAS's shared thread pool run several times slower than either alone)."""
    return two_cpus() and blas_threads() == 1


def _helper():
    """The one helper thread of the split products (started on first use)."""
    if not _HELPER:
        from concurrent.futures import ThreadPoolExecutor

        _HELPER.append(ThreadPoolExecutor(max_workers=1, thread_name_prefix="gpnarx-trmm"))
    return _HELPER[0]


def _dtrmm_rows(L: np.ndarray, B: np.ndarray, transpose: bool = False) -> None:
    """B[j] := L B[j] (``transpose``: L^T B[j]) for every row of the C-ordered block B (rows, N)."""
    import ctypes

    rows, N = B.shape
    n, m, one = ctypes.c_int(N), ctypes.c_int(rows), ctypes.c_double(1.0)
    # Fortran view: A = C-ordered L read column-major = L^T (upper); B^T := op(A) B^T with op(A) = A^T = L
    # (or op(A) = A = L^T)
    _DTRMM(b"L", b"U", b"N" if transpose else b"T", b"N", ctypes.byref(n), ctypes.byref(m), ctypes.byref(one),
           L.ctypes.data, ctypes.byref(n), B.ctypes.data, ctypes.byref(n))
