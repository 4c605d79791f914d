"""Service settings and request bounds.

Every bound is documented here (``DEFAULT_BOUNDS``), in the OpenAPI document (field descriptions
and the API description) and in docs/api.md. Each one can be changed with an environment variable
(``Settings.from_env``); the defaults are what the committed OpenAPI document describes.

=====================  ==========================  ===========  =============================
setting                 environment variable         default      exceeded ->
=====================  ==========================  ===========  =============================
max_samples             GPNARX_MAX_SAMPLES           65536        413, field ``u`` (or ``y``)
max_batch               GPNARX_MAX_BATCH             64           413, field ``requests``
mc_paths_default        GPNARX_MC_PATHS_DEFAULT      256          -
mc_paths_max            GPNARX_MC_PATHS_MAX          4096         422, field ``mc_paths``
max_mc_work             GPNARX_MAX_MC_WORK           2**24        413, field ``mc_paths``
max_body_bytes          GPNARX_MAX_BODY_BYTES        32 MiB       413, field ``body``
workers                 GPNARX_WORKERS               min(4, CPUs) -
queue_size              GPNARX_QUEUE_SIZE            16           503 + Retry-After
retry_after             GPNARX_RETRY_AFTER           2 (s)        -
request_timeout         GPNARX_REQUEST_TIMEOUT       120 (s)      504 (running) / 503 (queued)
api_key                 GPNARX_API_KEY               unset (off)  401 on /v1 routes
blas_threads            GPNARX_BLAS_THREADS          1            - (0: leave BLAS as it is)
mmap_threshold          GPNARX_MMAP_THRESHOLD        32 MiB       - (0: leave malloc as it is)
registry                GPNARX_REGISTRY              unset        - (a folder or an fsspec URL)
registry_poll           GPNARX_REGISTRY_POLL         30 (s)       - (0: no polling)
max_loaded              GPNARX_MAX_LOADED            8            - (built models kept in memory)
=====================  ==========================  ===========  =============================

``registry`` is a folder or an fsspec URL (``s3://bucket/prefix``, ``gs://...``, ``file://...``;
``model.storage`` says where credentials, endpoint and ``GPNARX_STORAGE_OPTIONS`` come from).
Every ``registry_poll`` seconds the server rescans its registry by itself (like ``POST
/v1/admin/reload``; unchanged versions are not verified again), so each of several replicas on one
registry serves a new version within that interval. A version is verified when it is first seen
and its model built on first use; at most ``max_loaded`` built models are kept (least recently
used dropped first, built again from the verified local files when asked for).

``max_mc_work`` bounds Monte Carlo path-steps (mc_paths x samples) per HTTP request; a batch
shares one budget across its records. ``queue_size`` is the number of jobs allowed to wait for a
worker on top of the ``workers`` running ones; when both are taken a request is shed with 503.

``request_timeout`` (seconds, may be fractional; 0 turns it off) bounds the time from
submission to answer of a prediction, loops, novelty or batch request. A job still waiting for a
worker at the deadline is dropped and answered 503 + Retry-After (the service was too busy); a job
already computing is answered 504 (the problem's ``limit`` is the limit in s) and cancelled at
its next checkpoint (every 256 samples of the free run, and between the records of a batch), which
frees its worker. A client that disconnects while its job waits or runs cancels it the same way,
so an abandoned request never holds a worker slot to the end. Choose it together with
``max_mc_work``: ``bench/bench_service.py`` measures the path-steps per second one worker serves
(docs/benchmarks.md); on a small machine a request at the default work bound (2**24 path-steps)
can need several minutes and is cut at 120 s, so raise the limit or lower the bound.

``blas_threads``: the service runs requests in parallel on its worker threads, and the per-step
matrix products of a free run are small (paths x training points), so multi-threaded BLAS inside
each request only oversubscribes the cores (measured on a loaded 2-core machine: a 256-sample,
128-path prediction took 3.8 s with OpenBLAS threads vs 0.33 s with one). The app therefore
limits BLAS to ``blas_threads`` threads per process (threadpoolctl) unless it is 0.

``mmap_threshold``: a free-run step allocates temporaries of paths x training points doubles
(256 x 600 x 8 B = 1.2 MB). glibc serves blocks above its mmap threshold (128 KiB until the
process has freed a large block) with a fresh mmap, so every step paid page faults: a fresh
server process predicted about 30 % slower than a process that had trained a model first
(measured 2.3 s vs 1.7 s for 512 samples x 128 paths). The app sets glibc's M_MMAP_THRESHOLD to
``mmap_threshold`` bytes (and M_TRIM_THRESHOLD to 4x that) with mallopt on Linux unless it is 0.
"""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field, replace

MiB = 1024 * 1024

#: Default bounds (documented in the OpenAPI document and docs/api.md).
DEFAULT_BOUNDS = {
    "max_samples": 65536,
    "max_batch": 64,
    "mc_paths_default": 256,
    "mc_paths_max": 4096,
    "max_mc_work": 2**24,
    "max_body_bytes": 32 * MiB,
}

ENV = {
    "max_samples": "GPNARX_MAX_SAMPLES",
    "max_batch": "GPNARX_MAX_BATCH",
    "mc_paths_default": "GPNARX_MC_PATHS_DEFAULT",
    "mc_paths_max": "GPNARX_MC_PATHS_MAX",
    "max_mc_work": "GPNARX_MAX_MC_WORK",
    "max_body_bytes": "GPNARX_MAX_BODY_BYTES",
    "workers": "GPNARX_WORKERS",
    "queue_size": "GPNARX_QUEUE_SIZE",
    "retry_after": "GPNARX_RETRY_AFTER",
    "request_timeout": "GPNARX_REQUEST_TIMEOUT",
    "api_key": "GPNARX_API_KEY",
    "registry": "GPNARX_REGISTRY",
    "blas_threads": "GPNARX_BLAS_THREADS",
    "mmap_threshold": "GPNARX_MMAP_THRESHOLD",
    "registry_poll": "GPNARX_REGISTRY_POLL",
    "max_loaded": "GPNARX_MAX_LOADED",
}


def _default_workers() -> int:
    return max(1, min(4, os.cpu_count() or 1))


@dataclass(frozen=True)
class Settings:
    """Runtime configuration of the HTTP service (see the module docstring for the table)."""

    max_samples: int = DEFAULT_BOUNDS["max_samples"]
    max_batch: int = DEFAULT_BOUNDS["max_batch"]
    mc_paths_default: int = DEFAULT_BOUNDS["mc_paths_default"]
    mc_paths_max: int = DEFAULT_BOUNDS["mc_paths_max"]
    max_mc_work: int = DEFAULT_BOUNDS["max_mc_work"]
    max_body_bytes: int = DEFAULT_BOUNDS["max_body_bytes"]
    workers: int = field(default_factory=_default_workers)
    queue_size: int = 16
    retry_after: int = 2
    #: seconds from submission to answer of a compute request (0: no limit)
    request_timeout: float = 120.0
    api_key: str | None = None
    registry: str | None = None
    blas_threads: int = 1
    mmap_threshold: int = 32 * MiB
    #: seconds between rescans of the registry for new, changed or removed versions (0: none)
    registry_poll: float = 30.0
    #: built models kept in memory (least recently used dropped first)
    max_loaded: int = 8
    #: reload the registry on SIGHUP (only where the event loop runs in the main thread)
    sighup_reload: bool = False

    def __post_init__(self):
        for name in ("max_samples", "max_batch", "mc_paths_default", "mc_paths_max", "max_mc_work",
                     "max_body_bytes", "workers", "retry_after", "max_loaded"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"setting {name} must be a positive integer, got {v!r}")
        if isinstance(self.queue_size, bool) or not isinstance(self.queue_size, int) or self.queue_size < 0:
            raise ValueError(f"setting queue_size must be a non-negative integer, got {self.queue_size!r}")
        for name in ("blas_threads", "mmap_threshold"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"setting {name} must be a non-negative integer, got {v!r}")
        for name in ("request_timeout", "registry_poll"):
            t = getattr(self, name)
            if isinstance(t, bool) or not isinstance(t, (int, float)) or not 0 <= t < float("inf"):
                raise ValueError(f"setting {name} must be a non-negative number of seconds, got {t!r}")
            object.__setattr__(self, name, float(t))
        if self.mc_paths_default > self.mc_paths_max:
            raise ValueError(f"setting mc_paths_default ({self.mc_paths_default}) exceeds mc_paths_max "
                             f"({self.mc_paths_max})")
        if self.api_key is not None and not str(self.api_key).strip():
            object.__setattr__(self, "api_key", None)

    @classmethod
    def from_env(cls, environ=None, **overrides) -> Settings:
        """Settings from ``GPNARX_*`` environment variables; ``overrides`` win."""
        env = os.environ if environ is None else environ
        kw: dict = {}
        for name, var in ENV.items():
            raw = env.get(var)
            if raw is None or raw == "":
                continue
            if name in ("api_key", "registry"):
                kw[name] = raw
            elif name in ("request_timeout", "registry_poll"):
                try:
                    kw[name] = float(raw)
                except ValueError:
                    raise ValueError(f"environment variable {var} must be a number of seconds, got {raw!r}") from None
            else:
                try:
                    kw[name] = int(raw.replace("_", ""))
                except ValueError:
                    raise ValueError(f"environment variable {var} must be an integer, got {raw!r}") from None
        kw.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**kw)

    def with_(self, **changes) -> Settings:
        return replace(self, **changes)

    def bounds(self) -> dict:
        """The request bounds in force (no secrets)."""
        d = asdict(self)
        return {k: d[k] for k in DEFAULT_BOUNDS}
