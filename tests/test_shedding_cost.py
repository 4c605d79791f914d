"""Load shedding by each request's own predicted time (``service.worker``: ``CostModel``, ``BoundedExecutor``).

One seconds-per-path-step average mixed small and large jobs and guessed wrong both ways:

- after many small calls (dominated by per-call and per-step overhead) it priced a large job at many times its
  cost: 6 of 8 large requests at the work bound got an instant 503 with a ``Retry-After`` of minutes while the
  2 admitted finished well inside the limit;
- after only large jobs it admitted every job whose *start* fitted the limit, so the last ones started,
  computed, and were answered 504 at the limit: their compute was wasted.

Scaled down here with controlled cost (jobs that sleep, reporting progress as the free run does): two
workers, a 3.6 s limit, small jobs of 20 ms (4096 path-steps) and large ones of 1 s (2^24 path-steps).
Eight large requests at once can be served six (three rounds of two by 3 s); the last two cannot finish by
3.6 s. Each must be served or refused by its own predicted finish: six served, two refused (503) early with an
honest wait, none timed out (504).
"""
from __future__ import annotations

import asyncio
import time

import pytest

from gpnarx.service.worker import BoundedExecutor, CancelToken, CostModel, JobSize, TimedOut, WontStart

SMALL_WORK, SMALL_S = 256 * 16, 0.02
LARGE_WORK, LARGE_S = 2**24, 1.0
LIMIT = 3.6


def _job(seconds: float, token: CancelToken | None = None):
    """Works ``seconds``, reporting progress and checking for cancellation every 20 ms (the free run's hooks)."""
    t0 = time.monotonic()
    while True:
        done = time.monotonic() - t0
        if done >= seconds:
            return "done"
        if token is not None:
            token.progress(done, seconds)
        time.sleep(min(0.02, seconds - done))


async def _flood(ex: BoundedExecutor, n: int = 8) -> dict:
    """``n`` large requests at once; how each ended, when, and the refusals' predicted waits."""
    t0 = time.monotonic()

    async def one():
        token = CancelToken()
        try:
            await ex.run(_job, LARGE_S, token, timeout=LIMIT, token=token, work=LARGE_WORK)
            return "served", time.monotonic() - t0, None
        except WontStart as exc:
            return "shed", time.monotonic() - t0, exc
        except TimedOut:
            return "timed out", time.monotonic() - t0, None

    out = await asyncio.gather(*(one() for _ in range(n)))
    kinds = [k for k, _, _ in out]
    return {"served": kinds.count("served"), "shed": kinds.count("shed"), "timed_out": kinds.count("timed out"),
            "shed_at": [t for k, t, _ in out if k == "shed"], "waits": [e.wait for k, _, e in out if k == "shed"],
            "after": [getattr(e, "retry_after", None) for k, _, e in out if k == "shed"]}


def test_small_calls_do_not_starve_large_ones():
    async def scenario():
        ex = BoundedExecutor(2, 16)
        for _ in range(30):  # many small calls: the only cost measured so far
            await ex.run(_job, SMALL_S, timeout=LIMIT, work=SMALL_WORK)
        try:
            return await _flood(ex)
        finally:
            ex.shutdown()

    got = asyncio.run(scenario())
    # before: 2 served, 6 refused at once with a predicted wait of about 80 s
    assert got["timed_out"] == 0, got
    assert got["served"] == 6 and got["shed"] == 2, got
    assert all(w < 2 * LIMIT for w in got["waits"]), got  # an honest wait, not minutes
    assert all(t < LIMIT - 1.0 for t in got["shed_at"]), got  # refused once known, long before the limit
    assert all(a is not None and a <= 2 for a in got["after"]), got


def test_nothing_is_admitted_that_cannot_finish_in_time():
    async def scenario():
        ex = BoundedExecutor(2, 16)
        await asyncio.gather(*(ex.run(_job, LARGE_S, timeout=LIMIT, work=LARGE_WORK) for _ in range(2)))
        try:
            return await _flood(ex)
        finally:
            ex.shutdown()

    got = asyncio.run(scenario())
    # before: all 8 admitted by their start; the last two timed out (504) at the limit, their compute wasted
    assert got["timed_out"] == 0 and got["served"] == 6 and got["shed"] == 2, got
    assert all(t < 0.5 for t in got["shed_at"]), got  # refused at once: their predicted finish is past the limit
    assert all(2.0 < w < 3.6 for w in got["waits"]), got  # they would start after the two rounds ahead (~3 s)
    assert all(a is not None and 0 < a <= 2 for a in got["after"]), got  # ~0.4 s past the limit: at least 1


# ------------------------------------------------------------------------------------------ the cost model
def test_the_cost_model_fits_overhead_per_step_and_per_path_step():
    m = CostModel()

    def cost(n, paths):  # per call + per step + per path-step
        return 0.01 + 2e-5 * n + 3e-8 * n * paths

    for n, paths in [(256, 16), (256, 256), (4096, 16), (4096, 4096), (1024, 64), (65536, 16)]:
        for _ in range(3):
            m.observe(JobSize.of("k", n, n * paths), cost(n, paths))
    for n, paths in [(2048, 512), (512, 16), (65536, 64)]:
        est = m.estimate(JobSize.of("k", n, n * paths))
        assert est == pytest.approx(cost(n, paths), rel=0.05), (n, paths, est, cost(n, paths))
    assert m.estimate(JobSize.of("other", 256, 4096)) is None  # another model / operation / method: unknown
    assert m.estimate(JobSize.of("k", 10**6, 10**9)) is None  # far beyond what was seen: unknown, not a guess
    assert m.bounds(JobSize.of("k", 10**6, 10**9))[0] >= cost(65536, 16)  # at least what a smaller job took


def test_a_running_jobs_progress_prices_jobs_of_its_size():
    m = CostModel()
    m.observe(JobSize.of("k", 256, 4096), 0.02)
    big = JobSize.of("k", 4096, 2**24)
    assert m.estimate(big) is None
    m.observe(big, 1.0, provisional=True)  # 5 % done after 50 ms
    assert m.estimate(big) == pytest.approx(1.0, rel=0.05)
    m.observe(big, 1.2)  # the finished job replaces its provisional estimate
    assert m.estimate(big) == pytest.approx(1.2, rel=0.05)
    m.observe(big, 0.5, provisional=True)  # a provisional one never overrides a measured one
    assert m.estimate(big) == pytest.approx(1.2, rel=0.05)
