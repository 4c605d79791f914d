"""Independent tasks of the offline work, run in this process or on a Dask cluster.

``TaskRunner(scheduler)`` is the one place that knows about ``dask.distributed`` (the optional
``dask`` extra). Without a scheduler every task runs here, in order, as a plain call (optionally on
local cores with joblib); with one, each task is submitted to the cluster. Data reaches the workers
as Python objects (numpy arrays, configs, fitted models), never as paths: ``share`` sends an object
once to every worker (a fitted model, a config) and ``send`` ships one object to the worker that will
use it (a record's arrays), so a worker needs neither the files nor the same folders as the client.

Tasks are plain module-level functions (pickled by reference, so the workers need the same
``gpnarx`` installed) whose results come back to the client, which alone writes files.
"""
from __future__ import annotations

import uuid
from collections.abc import Callable, Iterable, Iterator

from gpnarx.runtime import blas_threads_from_env, mmap_threshold_from_env, tune_malloc

__all__ = ["DASK_HINT", "TaskRunner", "check_dask"]

DASK_HINT = "a Dask scheduler needs dask.distributed: pip install 'gpnarx[dask]'"


def check_dask() -> None:
    """Raise ImportError with the install hint when dask.distributed is missing."""
    try:
        import distributed  # noqa: F401
    except ImportError as exc:
        raise ImportError(DASK_HINT) from exc


class Failed:
    """An item that failed before it could be submitted (for example a record file that did not read)."""

    def __init__(self, exc: BaseException):
        self.exc = exc


class TaskRunner:
    """Run independent tasks locally (``scheduler=None``) or on a Dask cluster.

    ``scheduler``: a scheduler address (``tcp://host:8786``) or an existing ``distributed.Client``.
    ``jobs``: local only; 1 runs the tasks in this process one after the other, another value runs
    them on local cores with joblib (-1: all cores).
    """

    def __init__(self, scheduler=None, *, jobs: int = 1, timeout: str = "30s"):
        self.scheduler = scheduler
        self.jobs = int(jobs)
        self.timeout = timeout
        self.client = None
        self._own = False

    # ------------------------------------------------------------------ lifetime
    def __enter__(self) -> TaskRunner:
        if self.scheduler is not None:
            check_dask()
            from distributed import Client

            if isinstance(self.scheduler, Client):
                self.client = self.scheduler
            else:
                try:
                    self.client = Client(str(self.scheduler), timeout=self.timeout)
                except OSError as exc:
                    raise OSError(f"--scheduler {self.scheduler}: cannot reach the Dask scheduler ({exc})") from None
                self._own = True
        return self

    def __exit__(self, *exc) -> None:
        if self._own and self.client is not None:
            self.client.close()
        self.client = None
        self._own = False

    @property
    def distributed(self) -> bool:
        return self.client is not None

    @property
    def where(self) -> str:
        """A short description for logs: 'local' or the scheduler address and its worker threads."""
        if self.client is None:
            return "local" if self.jobs == 1 else f"local ({self.jobs} jobs)"
        threads = sum(self.client.nthreads().values())
        return f"Dask {self.client.scheduler.address} ({threads} worker threads)"

    # ------------------------------------------------------------------ data
    def share(self, obj):
        """``obj`` for every task: sent once to every worker on Dask (a handle is returned)."""
        if self.client is None:
            return obj
        # in a one-item list: scatter would send a dict's or a list's items as separate keys
        return self.client.scatter([obj], broadcast=True, hash=False)[0]

    def send(self, obj):
        """``obj`` for one task: shipped to one worker on Dask (a handle is returned)."""
        if self.client is None:
            return obj
        return self.client.scatter([obj], hash=False)[0]

    # ------------------------------------------------------------------ tasks
    def imap(self, fn: Callable, calls: Iterable, *, window: int | None = None) -> Iterator[tuple]:
        """Run ``fn(*args)`` for each ``args`` tuple in ``calls`` (a ``Failed`` item stands for a call that
        could not be prepared); yields ``(index, result, exception)`` as tasks finish, exactly one of
        result/exception set. ``calls`` is consumed lazily: on Dask at most ``window`` tasks (default:
        twice the worker threads, at least 4) are in flight, so records can be read as they are needed.
        """
        if self.client is None:
            yield from self._imap_local(fn, calls)
        else:
            yield from self._imap_dask(fn, calls, window)

    def run(self, fn: Callable, calls: Iterable, on_done: Callable | None = None) -> list:
        """Results of ``fn(*args)`` for every call, in call order; the first exception is raised (and the
        tasks still pending are cancelled). ``on_done(index)`` is called as each task finishes."""
        out = {}
        gen = self.imap(fn, calls)
        try:
            for i, res, exc in gen:
                if exc is not None:
                    raise exc
                out[i] = res
                if on_done is not None:
                    on_done(i)
        finally:
            gen.close()
        return [out[i] for i in range(len(out))]

    def _imap_local(self, fn, calls):
        if self.jobs == 1:
            for i, args in enumerate(calls):
                if isinstance(args, Failed):
                    yield i, None, args.exc
                    continue
                try:
                    res = fn(*args)
                except Exception as exc:  # noqa: BLE001 (reported per task to the caller)
                    yield i, None, exc
                else:
                    yield i, res, None
            return
        from joblib import Parallel, delayed

        items = list(enumerate(calls))
        for i, args in items:
            if isinstance(args, Failed):
                yield i, None, args.exc
        todo = [(i, args) for i, args in items if not isinstance(args, Failed)]
        par = Parallel(n_jobs=self.jobs, return_as="generator_unordered")
        yield from par(delayed(_capture)(i, fn, args) for i, args in todo)

    def _imap_dask(self, fn, calls, window):
        from distributed import as_completed

        if window is None:
            window = max(4, 2 * sum(self.client.nthreads().values()))
        it = enumerate(calls)
        live = {}  # future key -> (index, future)
        done = as_completed()
        exhausted = False
        try:
            while True:
                while not exhausted and len(live) < window:
                    try:
                        i, args = next(it)
                    except StopIteration:
                        exhausted = True
                        break
                    if isinstance(args, Failed):
                        yield i, None, args.exc
                        continue
                    # keyed by the function's name, as the scheduler's dashboard and task counts show it
                    fut = self.client.submit(on_worker, fn, *args, key=f"{fn.__name__}-{uuid.uuid4().hex}")
                    live[fut.key] = (i, fut)
                    done.add(fut)
                if not live:
                    break
                fut = next(done)
                i, _ = live.pop(fut.key)
                try:
                    res = fut.result()
                except Exception as exc:  # noqa: BLE001 (the task's own error, reported per task)
                    yield i, None, exc
                else:
                    yield i, res, None
                finally:
                    fut.release()
        finally:
            if live:
                self.client.cancel([f for _, f in live.values()])


_TUNED = []


def on_worker(fn: Callable, *args):
    """Run ``fn(*args)`` in a worker process tuned for free runs as a local run is (``gpnarx.runtime``):
    glibc's mmap/trim thresholds set once per process (a Dask nanny starts workers with
    MALLOC_TRIM_THRESHOLD_=65536, which returns every step's temporaries to the kernel: free runs
    measured 3-4x slower), and BLAS held to ``GPNARX_BLAS_THREADS`` (default 1) threads during the task,
    so a worker computes what a local run computes, as fast."""
    from threadpoolctl import threadpool_limits  # here: a worker-side import, only where tasks run

    if not _TUNED:
        tune_malloc(mmap_threshold_from_env())
        _TUNED.append(True)
    blas = blas_threads_from_env()
    if not blas:
        return fn(*args)
    with threadpool_limits(limits=blas, user_api="blas"):
        return fn(*args)


def _capture(i, fn, args):
    try:
        return i, fn(*args), None
    except Exception as exc:  # noqa: BLE001 (reported per task to the caller)
        return i, None, exc
