"""Process-level tuning for free runs, shared by the HTTP service (``service/settings.py`` sets the
values) and the one-shot CLI commands (``gpnarx predict``, ``gpnarx novelty``).

A free run is thousands of small steps, each a few (paths x points) matrix products. Two process
settings matter for them. They are the process's, not the method's, so the package root holds them
(``gpnarx.runtime``), where ``training/``, ``service/`` and ``cli/`` all may import them:

* BLAS threads: on a machine whose cores are shared, multi-threaded OpenBLAS pays a scheduler
  wake-up per small product; one thread is the default (``GPNARX_BLAS_THREADS``, 0 = leave BLAS
  as it is). Measured by ``bench/bench_predict_e2e.py`` (tuned vs untuned subprocess). The CLI and the
  service set it for the process (``tune_for_free_run``, ``limit_blas``); the Python API's free run
  (``GPNARX.simulate``) sets it around itself (``free_run_blas``), in a process that has not decided,
  and restores the caller's settings after (``bench/bench_estimator_blas.py``).
* glibc's mmap threshold: temporaries of a few hundred KiB to MiB per step are otherwise served by
  fresh mmaps (page faults every step). ``GPNARX_MMAP_THRESHOLD`` bytes (default 32 MiB, 0 = leave
  malloc as it is) sets M_MMAP_THRESHOLD, and M_TRIM_THRESHOLD to 4x that.
"""
from __future__ import annotations

import contextlib
import os
import sys
import threading

MiB = 1024 * 1024
_LIMITERS = []
_DECIDED: list = []  # the BLAS threads this process was set to by limit_blas (0: left as it is), once decided
_SCOPED = {"depth": 0, "limiter": None}  # free_run_blas blocks running now and the limit the first one set
_SCOPED_LOCK = threading.Lock()


BLAS_THREADS_ENV = "GPNARX_BLAS_THREADS"
MMAP_THRESHOLD_ENV = "GPNARX_MMAP_THRESHOLD"
DEFAULT_BLAS_THREADS = 1
DEFAULT_MMAP_THRESHOLD = 32 * MiB


def env_int(name: str, default, environ=None, *, minimum: int | None = 0):
    """The integer in environment variable ``name`` (``environ``, default ``os.environ``; ``1_000``
    allowed), ``default`` when it is unset or blank; ``ValueError`` naming the variable when it is not
    an integer or is below ``minimum``. The one parser of the package's integer ``GPNARX_*`` variables
    (the service's settings use it too)."""
    raw = (os.environ if environ is None else environ).get(name)
    raw = "" if raw is None else str(raw).strip()
    if not raw:
        return default
    try:
        v = int(raw)
    except ValueError:
        raise ValueError(f"environment variable {name} must be an integer, got {raw!r}") from None
    if minimum is not None and v < minimum:
        raise ValueError(f"environment variable {name} must be >= {minimum}, got {v}")
    return v


def blas_threads_from_env(environ=None) -> int:
    """``GPNARX_BLAS_THREADS`` (default 1; 0 = leave BLAS as it is)."""
    return env_int(BLAS_THREADS_ENV, DEFAULT_BLAS_THREADS, environ)


def mmap_threshold_from_env(environ=None) -> int:
    """``GPNARX_MMAP_THRESHOLD`` in bytes (default 32 MiB; 0 = leave malloc as it is)."""
    return env_int(MMAP_THRESHOLD_ENV, DEFAULT_MMAP_THRESHOLD, environ)


def limit_blas(n: int) -> bool:
    """Limit BLAS to n threads in this process (0: leave as it is). Returns whether a limit was set. Either way
    the process has decided: ``free_run_blas`` blocks leave its BLAS alone from then on."""
    _DECIDED.append(int(n))
    if not n:
        return False
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl is a declared dependency
        return False
    _load_blas()  # first, so a limit set before the model is imported holds for both
    _LIMITERS.append(threadpool_limits(limits=int(n), user_api="blas"))
    return True


def _load_blas() -> None:
    # threadpoolctl limits the libraries loaded now: numpy's and scipy's BLAS (separate OpenBLAS builds, both
    # used by free runs)
    import numpy  # noqa: F401
    import scipy.linalg  # noqa: F401


@contextlib.contextmanager
def free_run_blas(blas_threads: int | None = None):
    """BLAS limited to the free-run setting while the block runs, the caller's settings restored after: the
    tuning of ``tune_for_free_run`` (``blas_threads``, else ``GPNARX_BLAS_THREADS``, default 1; 0 leaves BLAS as
    it is) for a process that never set it (the Python API: ``GPNARX.simulate`` runs its free run in this
    block). A process whose BLAS was already decided (``limit_blas``: the CLI, the service) is left alone.
    Blocks nested or running at once in several threads share one limit: the first in sets it, the last out
    restores it (BLAS thread counts are the process's)."""
    n = None
    if not _DECIDED:
        n = blas_threads_from_env() if blas_threads is None else int(blas_threads)
    if not n:
        yield
        return
    with _SCOPED_LOCK:
        if _SCOPED["depth"] == 0:
            try:
                from threadpoolctl import threadpool_limits
            except ImportError:  # pragma: no cover - threadpoolctl is a declared dependency
                limiter = None
            else:
                _load_blas()
                limiter = threadpool_limits(limits=n, user_api="blas")
            _SCOPED["limiter"] = limiter
        _SCOPED["depth"] += 1
    try:
        yield
    finally:
        with _SCOPED_LOCK:
            _SCOPED["depth"] -= 1
            if _SCOPED["depth"] == 0 and _SCOPED["limiter"] is not None:
                _SCOPED["limiter"].restore_original_limits()
                _SCOPED["limiter"] = None


def tune_malloc(mmap_threshold: int) -> bool:
    """glibc: serve blocks below ``mmap_threshold`` bytes from the heap (0 or non-glibc: no-op)."""
    if not mmap_threshold or not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3  # from malloc.h
        ok = libc.mallopt(m_mmap_threshold, int(min(mmap_threshold, 2**31 - 1)))
        ok = ok and libc.mallopt(m_trim_threshold, int(min(4 * mmap_threshold, 2**31 - 1)))
        return bool(ok)
    except (OSError, AttributeError):  # not glibc
        return False


def tune_for_free_run(blas_threads: int | None = None) -> dict:
    """Apply both settings (``blas_threads`` overrides ``GPNARX_BLAS_THREADS``); returns what was set."""
    n = blas_threads_from_env() if blas_threads is None else int(blas_threads)
    mm = mmap_threshold_from_env()
    return {"blas_threads": n if limit_blas(n) else 0, "mmap_threshold": mm if tune_malloc(mm) else 0}
