"""A bounded executor for CPU-heavy work (free-run prediction), with deadlines and cancellation.

``workers`` threads run jobs; at most ``queue_size`` more may wait. When all ``workers +
queue_size`` slots are taken, ``run`` raises ``Overloaded`` at once (the service answers 503 with
``Retry-After``) instead of queueing without limit. A slot is released when the job *finishes*
(not when the waiting request goes away), so the bound counts the real work in the process.
numpy/BLAS release the GIL, so the event loop keeps answering (``/health/live``) meanwhile.

Deadlines and abandoned requests: ``run(..., timeout=T, watch=W, token=C)`` stops waiting after
``T`` seconds (queue wait included) or as soon as the awaitable made by ``W()`` completes (the
service passes one that completes when the client disconnects). A job that has not started yet is cancelled and
its slot freed at once (``QueueTimeout`` / ``Abandoned``). A job already running cannot be killed
(it is a thread), so it is cancelled cooperatively: ``C`` (a ``CancelToken``) is set, and the job
raises ``Cancelled`` at its next checkpoint (``CancelToken.check``; the free run calls it through
its progress hook every 256 samples), which frees the slot; the caller gets ``TimedOut`` /
``Abandoned`` at once.

Admission by each job's own predicted time: a job comes with its size (``JobSize``: per part, a cost key
naming the model, version, operation, method and backend, its samples and its Monte Carlo path-steps), and
``CostModel`` predicts its seconds from the jobs of that key already run (a non-negative least-squares fit of
seconds = a + b x samples + c x path-steps over size buckets, so many small calls never crowd out what large
ones taught). A job is admitted only if its predicted finish (when a worker frees for it, by a first-in
first-out schedule of the running jobs' remaining time and the queued jobs' estimates, plus its own time) lies
within its deadline; else ``WontStart`` at once, with the time after which it would be admitted. A size the
model has not seen near enough (a different key, or far beyond the sizes measured) has no estimate: it counts
as the least a smaller measured job took, and once running, its progress (``CancelToken.progress``) prices it
and the jobs of its size within 5 % of its run; a queued job whose predicted finish no longer fits is then
dropped (``WontStart``) at once rather than answered 504 at its deadline.
"""
from __future__ import annotations

import asyncio
import contextvars
import heapq
import itertools
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Awaitable, Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

#: seconds between the checks of a queued job's predicted finish
SLICE = 0.5


class Overloaded(Exception):
    """All worker and queue slots are taken."""


class Cancelled(Exception):
    """Raised inside a job at a checkpoint once its ``CancelToken`` is set."""


class TimedOut(Exception):
    """The job was running when its deadline passed (it is being cancelled cooperatively)."""

    def __init__(self, timeout: float):
        super().__init__(f"the job did not finish within {timeout:g} s")
        self.timeout = timeout


class WontStart(Overloaded):
    """The job's predicted finish (the wait for a worker plus its own time) lies past its deadline: refused.

    ``wait``: seconds until a worker would be free for it; ``need``: its own predicted seconds (None: unknown,
    at least what a smaller job took); ``retry_after``: seconds after which it would be admitted."""

    def __init__(self, wait: float, timeout: float, need: float | None = None, retry_after: float | None = None):
        own = "" if not need else f" and this request about {need:.0f} s more"
        super().__init__(f"the work queued ahead needs about {wait:.0f} s{own}, past the request's time limit "
                         f"of {timeout:g} s")
        self.wait = wait
        self.timeout = timeout
        self.need = need
        self.retry_after = retry_after


class QueueTimeout(Overloaded):
    """The deadline passed while the job was still waiting for a worker (it was cancelled)."""

    def __init__(self, timeout: float):
        super().__init__(f"the job waited {timeout:g} s for a worker without starting")
        self.timeout = timeout


class Abandoned(Exception):
    """The ``watch()`` awaitable completed first (the client went away); the job was cancelled."""


class CancelToken:
    """Cooperative cancellation flag shared by a request and its job."""

    def __init__(self):
        self._event = threading.Event()
        self.reason = ""
        self.on_progress: Callable[[float], None] | None = None  # set by BoundedExecutor: share of the job done
        #: (share of the job done before this part, share this part is of the job): a batch sets it per record
        self.span: tuple[float, float] = (0.0, 1.0)

    def cancel(self, reason: str = "cancelled") -> None:
        self.reason = reason
        self._event.set()

    @property
    def cancelled(self) -> bool:
        return self._event.is_set()

    def check(self) -> None:
        if self._event.is_set():
            raise Cancelled(self.reason)

    def progress(self, done: int, total: int) -> None:
        """A ``progress(done, total)`` hook for ``GPNARX.simulate``: a checkpoint."""
        self.check()
        if self.on_progress is not None and total > 0:
            self.on_progress(self.span[0] + self.span[1] * min(1.0, done / total))


def _consume(fut) -> None:
    """Mark an abandoned future's outcome as retrieved (no 'exception was never retrieved' log)."""
    if not fut.cancelled():
        fut.exception()


@dataclass(frozen=True)
class JobSize:
    """What a job computes, for its time estimate: parts of (cost key, samples, Monte Carlo path-steps).

    The key names what sets the cost per sample and per path-step (model, version, operation, method, backend);
    a batch has one part per record."""

    parts: tuple[tuple[str, float, float], ...]

    @classmethod
    def of(cls, key: str, samples: float, path_steps: float = 0.0) -> JobSize:
        return cls(((str(key), max(0.0, float(samples)), max(0.0, float(path_steps))),))

    @classmethod
    def work(cls, work: float) -> JobSize:
        """A job known only by its work units (any unit, the same for comparable jobs)."""
        return cls.of("", 0.0, max(float(work), 1.0))

    def __add__(self, other: JobSize) -> JobSize:
        return JobSize(self.parts + other.parts)


class CostModel:
    """Seconds a job takes, from the jobs already run: per cost key, a fit of seconds = a + b x samples +
    c x path-steps (a, b, c >= 0).

    Observations are kept per size bucket (a factor 2 in samples and in path-steps; each bucket an exponential
    average, the last ``BUCKETS`` buckets per key), so the fit sees every size measured however many jobs of
    one size ran. The fit minimises relative errors (a 20 ms call weighs as much as a 40 s one). A size more
    than ``RANGE`` times beyond the sizes measured (or of a key never run) has no estimate: ``bounds`` gives
    what is known (at least what a measured job at most as large took, at most what one at least as large
    took). A provisional observation (a running job's progress) stands in a bucket until a finished job's
    replaces it."""

    BUCKETS = 32
    KEYS = 256
    RANGE = 4.0
    ALPHA = 0.3  # weight of a new observation in its bucket's average

    def __init__(self):
        # key -> {bucket: [samples, path-steps, seconds, provisional, seq]}
        self._keys: OrderedDict[str, dict] = OrderedDict()
        self._fits: dict[str, tuple | None] = {}
        self._seq = itertools.count()
        self._lock = threading.Lock()

    @staticmethod
    def _bucket(samples: float, path_steps: float) -> tuple[int, int]:
        return round(math.log2(1.0 + samples)), round(math.log2(1.0 + path_steps))

    def observe(self, size: JobSize | float, seconds: float, provisional: bool = False) -> None:
        """Record that a job of ``size`` took (``provisional``: will take) ``seconds``."""
        size = size if isinstance(size, JobSize) else JobSize.work(size)
        if not (seconds > 0 and math.isfinite(seconds)) or not size.parts:
            return
        parts = size.parts
        if len(parts) > 1:  # a batch: its time shared by its records' estimates (else by their work)
            if provisional:
                return
            ests = [self._estimate_part(*p) for p in parts]
            if any(e is None for e in ests):
                if len({k for k, _, _ in parts}) > 1:
                    return
                ests = [p or s for _, s, p in parts]
            total = sum(ests)
            if total <= 0:
                return
            for part, e in zip(parts, ests):
                self._observe_part(*part, seconds * e / total, False)
            return
        self._observe_part(*parts[0], seconds, provisional)

    def _observe_part(self, key: str, samples: float, path_steps: float, seconds: float, provisional: bool) -> None:
        if not (seconds > 0 and math.isfinite(seconds)):
            return
        with self._lock:
            buckets = self._keys.setdefault(key, {})
            self._keys.move_to_end(key)
            while len(self._keys) > self.KEYS:
                old, _ = self._keys.popitem(last=False)
                self._fits.pop(old, None)
            b = self._bucket(samples, path_steps)
            cur = buckets.get(b)
            seq = next(self._seq)
            if cur is None or cur[3]:  # new, or a provisional one: replaced whole
                buckets[b] = [samples, path_steps, seconds, provisional, seq]
            elif provisional:  # a measured bucket is not moved by a running job's guess
                return
            else:
                a = self.ALPHA
                buckets[b] = [(1 - a) * cur[0] + a * samples, (1 - a) * cur[1] + a * path_steps,
                              (1 - a) * cur[2] + a * seconds, False, seq]
            if len(buckets) > self.BUCKETS:
                del buckets[min(buckets, key=lambda k: buckets[k][4])]
            self._fits.pop(key, None)

    def _fit(self, key: str):
        """(coefficients for [1, samples, path-steps], low and high of each feature measured) or None."""
        if key in self._fits:
            return self._fits[key]
        if key not in self._keys:
            return None
        rows = np.array([v[:3] for v in self._keys.get(key, {}).values()], dtype=float)
        fit = None
        if len(rows):
            X = np.column_stack([np.ones(len(rows)), rows[:, 0], rows[:, 1]])
            t = rows[:, 2]
            used = [0] + [c for c in (1, 2) if np.any(X[:, c] > 0)]
            scale = X.max(axis=0)
            scale[scale <= 0] = 1.0
            A = X / scale / t[:, None]  # relative errors: each row over its seconds
            best = None
            for r in range(len(used), 0, -1):
                for cols in itertools.combinations(used, r):
                    coef, *_ = np.linalg.lstsq(A[:, cols], np.ones(len(t)), rcond=None)
                    if np.any(coef < 0):
                        continue
                    res = float(np.sum((A[:, cols] @ coef - 1.0) ** 2))
                    if best is None or res < best[0] - 1e-12:
                        full = np.zeros(3)
                        full[list(cols)] = coef / scale[list(cols)]
                        best = (res, full)
            if best is not None:
                fit = (best[1], X.min(axis=0), X.max(axis=0), used)
        self._fits[key] = fit
        return fit

    def _estimate_part(self, key: str, samples: float, path_steps: float) -> float | None:
        with self._lock:
            fit = self._fit(key)
        if fit is None:
            return None
        coef, lo, hi, used = fit
        x = np.array([1.0, samples, path_steps])
        for c in (1, 2):
            if x[c] > 0 and (c not in used or x[c] > hi[c] * self.RANGE or x[c] < lo[c] / self.RANGE):
                return None
        est = float(coef @ x)
        low, high = self._bounds_part(key, samples, path_steps)
        if low <= high:
            est = min(max(est, low), high)
        return est if est > 0 else None

    def _bounds_part(self, key: str, samples: float, path_steps: float) -> tuple[float, float]:
        low, high = 0.0, math.inf
        with self._lock:
            for s, p, t, _, _ in self._keys.get(key, {}).values():
                if s <= samples and p <= path_steps:
                    low = max(low, t)
                if s >= samples and p >= path_steps:
                    high = min(high, t)
        return low, high

    def estimate(self, size: JobSize | float) -> float | None:
        """Predicted seconds of a job of ``size``; None when some part has no estimate."""
        size = size if isinstance(size, JobSize) else JobSize.work(size)
        total = 0.0
        for part in size.parts:
            e = self._estimate_part(*part)
            if e is None:
                return None
            total += e
        return total

    def bounds(self, size: JobSize | float) -> tuple[float, float]:
        """(at least, at most) seconds of a job of ``size`` from the jobs measured (0 and inf when unknown)."""
        size = size if isinstance(size, JobSize) else JobSize.work(size)
        low, high = 0.0, 0.0
        for part in size.parts:
            lo, hi = self._bounds_part(*part)
            low, high = low + lo, high + hi
        return low, high


class _Job:
    """A submitted job as the schedule sees it."""

    __slots__ = ("size", "started", "share", "share_at", "priced")

    def __init__(self, size: JobSize):
        self.size = size
        self.started: float | None = None  # time.monotonic() when a worker took it
        self.share = 0.0  # share done at share_at (CancelToken.progress)
        self.share_at = 0.0
        self.priced = False  # its progress gave the cost model a provisional observation


#: share of a running job done from which its progress prices it
PROGRESS_SHARE = 0.05


class BoundedExecutor:
    def __init__(self, workers: int, queue_size: int):
        if workers < 1 or queue_size < 0:
            raise ValueError("workers must be >= 1 and queue_size >= 0")
        self.workers = int(workers)
        self.queue_size = int(queue_size)
        self.capacity = self.workers + self.queue_size
        self._pool = ThreadPoolExecutor(max_workers=self.workers, thread_name_prefix="gpnarx-worker")
        self._lock = threading.Lock()
        self.model = CostModel()
        self._jobs: dict[int, _Job] = {}  # submitted and not finished (running + waiting), in submission order
        self._seq = 0
        self._closed = False

    @property
    def pending(self) -> int:
        return len(self._jobs)

    # ---------------------------------------------------------------- the schedule
    def _cost(self, job: _Job) -> float:
        """A queued job's predicted seconds (unknown: the least a measured job at most as large took)."""
        est = self.model.estimate(job.size)
        return est if est is not None else self.model.bounds(job.size)[0]

    def _remaining(self, job: _Job, now: float) -> float:
        """A running job's predicted seconds left: from its progress once ``PROGRESS_SHARE`` is done, else
        from its estimate."""
        elapsed = now - job.started
        if job.share >= PROGRESS_SHARE:
            return max(0.0, (job.share_at - job.started) / job.share - elapsed)
        return max(0.0, self._cost(job) - elapsed)

    def _schedule(self, now: float, before: int | None = None) -> tuple[float, list[float]]:
        """(seconds until a worker frees for the next job, the predicted finishes of the jobs ahead) when the
        jobs submitted before ``before`` (None: all) run first in, first out on the workers."""
        free = []
        queued = []
        for seq, job in self._jobs.items():
            if before is not None and seq >= before:
                break
            if job.started is not None:
                free.append(self._remaining(job, now))
            else:
                queued.append(job)
        free = sorted(free)[: self.workers]
        free += [0.0] * (self.workers - len(free))
        heapq.heapify(free)
        finishes = list(free)
        for job in queued:
            t = heapq.heappop(free) + self._cost(job)
            heapq.heappush(free, t)
            finishes.append(t)
        return free[0], finishes

    def wait_estimate(self) -> float:
        """Seconds a job submitted now would wait for a worker (0 when one is free)."""
        with self._lock:
            return self._schedule(time.monotonic())[0]

    def retry_after(self, need: float = 0.0, timeout: float | None = None) -> float:
        """Seconds after which a job of ``need`` seconds would be admitted: once a slot is free and, with a
        ``timeout``, once the wait for a worker plus ``need`` fits it (0: now)."""
        with self._lock:
            wait, finishes = self._schedule(time.monotonic())
            full = len(self._jobs) >= self.capacity
        after = min((f for f in finishes if f > 0), default=0.0) if full else 0.0
        if timeout:
            after = max(after, wait + need - timeout)
        return max(0.0, after)

    def _release(self, seq: int) -> None:
        with self._lock:
            self._jobs.pop(seq, None)

    async def run(self, fn: Callable[..., Any], *args: Any, timeout: float | None = None,
                  watch: Callable[[], Awaitable] | None = None, token: CancelToken | None = None,
                  work: float = 1.0) -> Any:
        """Run ``fn(*args)`` on a worker thread.

        Raises ``Overloaded`` when no slot is free, ``WontStart`` (an ``Overloaded``) at once when the
        job's predicted finish (the wait for a worker and its own time, ``CostModel``) lies past
        ``timeout``, ``QueueTimeout`` / ``TimedOut`` when ``timeout`` seconds pass before / after the job
        started, ``Abandoned`` when ``watch()`` completes first (it is called once the job is submitted).
        ``token`` (also passed to ``fn`` by the caller) is set when a running job must stop; its progress
        prices the job. ``work``: the job's size, a ``JobSize`` or a number of work units (any unit, the
        same for comparable jobs).
        """
        size = work if isinstance(work, JobSize) else JobSize.work(work)
        entry = _Job(size)
        with self._lock:
            if self._closed:
                raise Overloaded("the service is shutting down")
            if len(self._jobs) >= self.capacity:
                raise Overloaded(f"all {self.workers} workers are busy and {self.queue_size} jobs are waiting")
            if timeout:
                wait = self._schedule(time.monotonic())[0]
                need = self._cost(entry)
                if wait + need > timeout:
                    raise WontStart(wait, timeout, need, retry_after=wait + need - timeout)
            self._seq += 1
            seq = self._seq
            self._jobs[seq] = entry

        def progressed(share: float) -> None:  # the running job's progress: its remaining time, and its price
            if entry.started is None:
                return
            now = time.monotonic()
            entry.share, entry.share_at = share, now
            if share >= PROGRESS_SHARE and not entry.priced:
                entry.priced = True
                self.model.observe(size, (now - entry.started) / share, provisional=True)

        if token is not None:
            token.on_progress = progressed

        def job():
            t0 = time.monotonic()
            entry.started = t0
            out = fn(*args)
            self.model.observe(size, time.monotonic() - t0)  # finished jobs only: a cancelled one says nothing
            return out

        try:
            fut = self._pool.submit(contextvars.copy_context().run, job)  # the request's id for its logs
        except BaseException:
            self._release(seq)
            raise
        fut.add_done_callback(lambda _f: self._release(seq))
        afut = asyncio.wrap_future(fut)
        if not timeout and watch is None:
            return await afut
        watcher = asyncio.ensure_future(watch()) if watch is not None else None
        try:
            waiting = {afut} if watcher is None else {afut, watcher}
            loop = asyncio.get_running_loop()
            end = loop.time() + timeout if timeout else None
            while True:  # in slices: a queued job that can no longer finish in time is refused as soon as known
                left = None if end is None else max(0.0, end - loop.time())
                done, _ = await asyncio.wait(waiting, timeout=None if left is None else min(left, SLICE),
                                             return_when=asyncio.FIRST_COMPLETED)
                if done or fut.done() or (end is not None and loop.time() >= end):
                    break
                if entry.started is None and end is not None:
                    with self._lock:
                        wait = self._schedule(time.monotonic(), before=seq)[0]
                        need = self._cost(entry)
                    left = end - loop.time()
                    if wait + need > left and fut.cancel():
                        afut.add_done_callback(_consume)
                        raise WontStart(wait, timeout, need, retry_after=wait + need - left)
            if afut in done or fut.done():
                return await afut
            gone = watcher is not None and watcher in done
            afut.add_done_callback(_consume)
            if fut.cancel():  # still waiting for a worker: dropped, slot freed now
                if gone:
                    raise Abandoned("the client disconnected while the job waited for a worker")
                raise QueueTimeout(timeout)
            if token is not None:
                token.cancel("client disconnected" if gone else f"deadline of {timeout:g} s passed")
            if gone:
                raise Abandoned("the client disconnected while the job ran")
            raise TimedOut(timeout)
        except asyncio.CancelledError:  # the request task itself was cancelled (server shutdown, ...)
            afut.add_done_callback(_consume)
            if not fut.cancel() and token is not None:
                token.cancel("request cancelled")
            raise
        finally:
            if watcher is not None and not watcher.done():
                watcher.cancel()

    def shutdown(self) -> None:
        with self._lock:
            self._closed = True
        self._pool.shutdown(wait=False, cancel_futures=True)
