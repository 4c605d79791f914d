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
        self._closed = False

    @property
    def pending(self) -> int:
        return self._pending

    def _release(self, _fut=None) -> None:
        with self._lock:
            self._pending -= 1

    async def run(self, fn: Callable[..., Any], *args: Any, timeout: float | None = None,
                  watch: Callable[[], Awaitable] | None = None, token: CancelToken | None = None) -> Any:
        """Run ``fn(*args)`` on a worker thread.

        Raises ``Overloaded`` when no slot is free, ``QueueTimeout`` / ``TimedOut`` when ``timeout``
        seconds pass before / after the job started, ``Abandoned`` when ``watch()`` completes first (it is
        called once the job is submitted).
        ``token`` (also passed to ``fn`` by the caller) is set when a running job must stop.
        """
        with self._lock:
            if self._closed:
                raise Overloaded("the service is shutting down")
            if self._pending >= self.capacity:
                raise Overloaded(f"all {self.workers} workers are busy and {self.queue_size} jobs are waiting")
            self._pending += 1
        try:
            fut = self._pool.submit(contextvars.copy_context().run, fn, *args)  # the request's id for its logs
        except BaseException:
            self._release()
            raise
        fut.add_done_callback(self._release)
        afut = asyncio.wrap_future(fut)
        if not timeout and watch is None:
            return await afut
        watcher = asyncio.ensure_future(watch()) if watch is not None else None
        try:
            waiting = {afut} if watcher is None else {afut, watcher}
            done, _ = await asyncio.wait(waiting, timeout=timeout or None, return_when=asyncio.FIRST_COMPLETED)
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
