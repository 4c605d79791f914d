"""A bounded executor for CPU-heavy work (free-run prediction).

``workers`` threads run jobs; at most ``queue_size`` more may wait. When all ``workers +
queue_size`` slots are taken, ``run`` raises ``Overloaded`` at once (the service answers 503 with
``Retry-After``) instead of queueing without limit. A slot is released when the job *finishes*
(not when the waiting request goes away), so the bound counts the real work in the process.
numpy/BLAS release the GIL, so the event loop keeps answering (``/health/live``) meanwhile.
"""
from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any


class Overloaded(Exception):
    """All worker and queue slots are taken."""


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

    async def run(self, fn: Callable[..., Any], *args: Any) -> Any:
        """Run ``fn(*args)`` on a worker thread; raises ``Overloaded`` when no slot is free."""
        with self._lock:
            if self._closed:
                raise Overloaded("the service is shutting down")
            if self._pending >= self.capacity:
                raise Overloaded(f"all {self.workers} workers are busy and {self.queue_size} jobs are waiting")
            self._pending += 1
        try:
            fut = self._pool.submit(fn, *args)
        except BaseException:
            self._release()
            raise
        fut.add_done_callback(self._release)
        return await asyncio.wrap_future(fut)

    def shutdown(self) -> None:
        with self._lock:
            self._closed = True
        self._pool.shutdown(wait=False, cancel_futures=True)
