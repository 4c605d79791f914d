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
"""
from __future__ import annotations

import asyncio
import contextvars
import threading
import time
from collections.abc import Awaitable, Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any


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
    """The work already queued would keep a new job waiting past its deadline: refused at once."""

    def __init__(self, wait: float, timeout: float):
        super().__init__(f"the work queued ahead needs about {wait:.0f} s, more than the request's time limit "
                         f"of {timeout:g} s")
        self.wait = wait
        self.timeout = timeout


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
            self.on_progress(done / total)


def _consume(fut) -> None:
    """Mark an abandoned future's outcome as retrieved (no 'exception was never retrieved' log)."""
    if not fut.cancelled():
        fut.exception()


class BoundedExecutor:
    def __init__(self, workers: int, queue_size: int):
        if workers < 1 or queue_size < 0:
            raise ValueError("workers must be >= 1 and queue_size >= 0")
        self.workers = int(workers)
        self.queue_size = int(queue_size)
        self.capacity = self.workers + self.queue_size
        self._pool = ThreadPoolExecutor(max_workers=self.workers, thread_name_prefix="gpnarx-worker")
        self._lock = threading.Lock()
        self._pending = 0  # submitted and not finished (running + waiting)
        self._pending_work = 0.0  # their work units (Monte Carlo path-steps, or samples)
        self._sec_per_work: float | None = None  # moving average of a worker's seconds per work unit
        self._queued: dict[int, float] = {}  # work of the jobs not started yet, in submission order
        self._seq = 0
        self._closed = False

    @property
    def pending(self) -> int:
        return self._pending

    @property
    def pending_work(self) -> float:
        return self._pending_work

    def wait_estimate(self) -> float | None:
        """Seconds a job submitted now would wait for a worker (0 when one is free; None before
        any job has finished): the queued and running work over the measured rate and the workers."""
        with self._lock:
            return self._wait_locked()

    def _wait_locked(self) -> float | None:
        if self._pending < self.workers:
            return 0.0
        if self._sec_per_work is None:
            return None
        return self._pending_work * self._sec_per_work / self.workers

    def _observe(self, work: float, seconds: float) -> None:
        if work <= 0:
            return
        rate = seconds / work
        with self._lock:
            self._sec_per_work = rate if self._sec_per_work is None else 0.7 * self._sec_per_work + 0.3 * rate

    def _start_estimate(self, seq: int) -> float | None:
        """Seconds until queued job ``seq`` starts: the running work and the queued work ahead of it
        (the pool is first in, first out) over the measured rate and the workers; None: no rate yet."""
        with self._lock:
            if self._sec_per_work is None or seq not in self._queued:
                return None
            queued = sum(self._queued.values())
            ahead = sum(w for s, w in self._queued.items() if s < seq)
            return (self._pending_work - queued + ahead) * self._sec_per_work / self.workers

    def _release(self, work: float = 1.0, seq: int | None = None) -> None:
        with self._lock:
            self._queued.pop(seq, None)
            self._pending -= 1
            self._pending_work = max(0.0, self._pending_work - work)

    async def run(self, fn: Callable[..., Any], *args: Any, timeout: float | None = None,
                  watch: Callable[[], Awaitable] | None = None, token: CancelToken | None = None,
                  work: float = 1.0) -> Any:
        """Run ``fn(*args)`` on a worker thread.

        Raises ``Overloaded`` when no slot is free, ``WontStart`` (an ``Overloaded``) at once when the
        work queued ahead would keep the job waiting past ``timeout`` (``wait_estimate``),
        ``QueueTimeout`` / ``TimedOut`` when ``timeout`` seconds pass before / after the job started,
        ``Abandoned`` when ``watch()`` completes first (it is called once the job is submitted).
        ``token`` (also passed to ``fn`` by the caller) is set when a running job must stop. ``work``:
        the job's size (Monte Carlo path-steps; any unit, the same for every job) for the estimate.
        """
        work = max(float(work), 1.0)
        with self._lock:
            if self._closed:
                raise Overloaded("the service is shutting down")
            if self._pending >= self.capacity:
                raise Overloaded(f"all {self.workers} workers are busy and {self.queue_size} jobs are waiting")
            wait = self._wait_locked()
            if timeout and wait is not None and wait > timeout:
                raise WontStart(wait, timeout)
            self._pending += 1
            self._pending_work += work
            self._seq += 1
            seq = self._seq
            self._queued[seq] = work

        t_start: list[float] = []

        def progressed(share: float) -> None:  # before any job has finished: estimate from a running one
            if self._sec_per_work is None and share >= 0.05 and t_start:
                with self._lock:
                    if self._sec_per_work is None:
                        self._sec_per_work = (time.perf_counter() - t_start[0]) / (work * share)

        if token is not None:
            token.on_progress = progressed

        def job():
            t0 = time.perf_counter()
            t_start.append(t0)
            with self._lock:
                self._queued.pop(seq, None)
            out = fn(*args)
            self._observe(work, time.perf_counter() - t0)  # finished jobs only: a cancelled one says nothing
            return out

        try:
            fut = self._pool.submit(contextvars.copy_context().run, job)  # the request's id for its logs
        except BaseException:
            self._release(work, seq)
            raise
        fut.add_done_callback(lambda _f: self._release(work, seq))
        afut = asyncio.wrap_future(fut)
        if not timeout and watch is None:
            return await afut
        watcher = asyncio.ensure_future(watch()) if watch is not None else None
        try:
            waiting = {afut} if watcher is None else {afut, watcher}
            loop = asyncio.get_running_loop()
            end = loop.time() + timeout if timeout else None
            while True:  # in slices: a queued job that can no longer start in time is refused as soon as known
                left = None if end is None else max(0.0, end - loop.time())
                done, _ = await asyncio.wait(waiting, timeout=None if left is None else min(left, 1.0),
                                             return_when=asyncio.FIRST_COMPLETED)
                if done or fut.done() or (end is not None and loop.time() >= end):
                    break
                if not t_start and end is not None:
                    wait = self._start_estimate(seq)
                    if wait is not None and wait > end - loop.time() and fut.cancel():
                        afut.add_done_callback(_consume)
                        raise WontStart(wait, timeout)
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
