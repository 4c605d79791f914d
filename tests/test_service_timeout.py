"""Per-request time limit (GPNARX_REQUEST_TIMEOUT) and cancellation of abandoned requests.

- ``BoundedExecutor`` alone: a queued job past its deadline is dropped at once (``QueueTimeout``,
  slot freed), a running one gets ``TimedOut`` and is stopped at its next checkpoint through its
  ``CancelToken``; a completed ``watch()`` (client gone) cancels the job the same way.
- A real uvicorn server and the real model with a tiny limit: a long prediction is answered 504
  (problem detail naming ``mc_paths`` and the limit) instead of hanging, and the only worker is
  free again long before the prediction would have finished; a client that disconnects frees it
  too; a request still queued at its deadline is answered 503 + Retry-After.
"""
from __future__ import annotations

import asyncio
import threading
import time

import httpx
import numpy as np
import pytest
from test_service_support import FS, LiveServer, built_registry, multisine, short_record

from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings
from gpnarx.service.worker import (
    Abandoned,
    BoundedExecutor,
    Cancelled,
    CancelToken,
    QueueTimeout,
    TimedOut,
)

PROBLEM = "application/problem+json"


def _wait(cond, timeout):
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > timeout:
            return False
        time.sleep(0.01)
    return True


def _slow_job(token: CancelToken, started: threading.Event, seconds: float = 30.0):
    """Works for ``seconds``, checking ``token`` every 10 ms (a checkpoint)."""
    started.set()
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        token.check()
        time.sleep(0.01)
    return "finished"


# ------------------------------------------------------------------------------------------ executor
def test_executor_deadline_queue_and_watch():
    async def scenario():
        ex = BoundedExecutor(workers=1, queue_size=2)
        try:
            # a job within its deadline returns its value; a job's own exception propagates
            assert await ex.run(lambda: 42, timeout=5.0) == 42
            with pytest.raises(ZeroDivisionError):
                await ex.run(lambda: 1 / 0, timeout=5.0)
            assert ex.pending == 0

            tok_a, started = CancelToken(), threading.Event()
            t0 = time.perf_counter()
            a = asyncio.ensure_future(ex.run(_slow_job, tok_a, started, timeout=0.6, token=tok_a))
            await asyncio.to_thread(started.wait, 10)
            # B waits for the busy worker and its deadline passes first: dropped, slot freed at once
            tok_b = CancelToken()
            with pytest.raises(QueueTimeout):
                await ex.run(_slow_job, tok_b, threading.Event(), timeout=0.1, token=tok_b)
            assert ex.pending == 1 and not tok_b.cancelled
            # A was running at its deadline: TimedOut at the deadline, token set, job stops at a checkpoint
            with pytest.raises(TimedOut):
                await a
            assert 0.5 < time.perf_counter() - t0 < 3.0
            assert tok_a.cancelled and "deadline" in tok_a.reason
            assert await asyncio.to_thread(_wait, lambda: ex.pending == 0, 5.0)

            # the watch (client gone) completes first: Abandoned, the running job is cancelled
            gone = asyncio.Event()
            tok_c, started_c = CancelToken(), threading.Event()
            c = asyncio.ensure_future(ex.run(_slow_job, tok_c, started_c, watch=gone.wait, token=tok_c))
            await asyncio.to_thread(started_c.wait, 10)
            gone.set()
            with pytest.raises(Abandoned):
                await c
            assert tok_c.cancelled and "disconnected" in tok_c.reason
            assert await asyncio.to_thread(_wait, lambda: ex.pending == 0, 5.0)
        finally:
            ex.shutdown()

    asyncio.run(scenario())


def test_cancel_token():
    tok = CancelToken()
    tok.check()
    tok.progress(1, 10)
    tok.cancel("why")
    with pytest.raises(Cancelled, match="why"):
        tok.progress(2, 10)


def test_request_timeout_setting():
    assert Settings().request_timeout == 120.0
    assert Settings.from_env({"GPNARX_REQUEST_TIMEOUT": "0.25"}).request_timeout == 0.25
    assert Settings.from_env({"GPNARX_REQUEST_TIMEOUT": "0"}).request_timeout == 0.0
    with pytest.raises(ValueError, match="GPNARX_REQUEST_TIMEOUT"):
        Settings.from_env({"GPNARX_REQUEST_TIMEOUT": "soon"})
    for bad in (-1, float("inf"), float("nan"), True, "5"):
        with pytest.raises(ValueError, match="request_timeout"):
            Settings(request_timeout=bad)


# ------------------------------------------------------------------------------------------ real server, real model
@pytest.fixture(scope="module")
def rate():
    """Monte Carlo path-steps/s of the test model in this process, right now (for the 'long' bounds)."""
    model = built_registry().model
    u = multisine(512, 77)
    t0 = time.perf_counter()
    model.simulate(u, n_paths=128, seed=0)
    return 512 * 128 / (time.perf_counter() - t0)


def _long_body(rate, seconds=120.0, paths=256):
    """A record long enough that its full prediction takes about ``seconds`` here."""
    n = int(min(60000, max(4096, seconds * rate / paths)))
    return {"u": multisine(n, 31).tolist(), "fs": FS, "mc_paths": paths, "seed": 0}, n * paths / rate


def test_predict_past_time_limit_is_504_and_frees_the_worker(rate):
    app = create_app(built_registry().root, Settings(workers=1, queue_size=0, request_timeout=0.5))
    ex = app.state.service.executor
    body, full_s = _long_body(rate)
    with LiveServer(app) as srv, httpx.Client(base_url=srv.url, timeout=60) as c:
        t0 = time.perf_counter()
        r = c.post("/v1/models/boucwen/predict", json=body)
        took = time.perf_counter() - t0
        assert r.status_code == 504, r.text[:300]
        assert r.headers["content-type"].startswith(PROBLEM)
        p = r.json()
        assert p["status"] == 504 and p["field"] == "mc_paths" and p["limit"] == 0.5
        assert "0.5 s" in p["detail"] and "GPNARX_REQUEST_TIMEOUT" in p["detail"]
        assert took < 5.0, took  # answered at the deadline (plus parsing), not after the computation
        # the job stops at its next checkpoint (256 samples): the worker is free long before the
        # full prediction (full_s, measured rate) would have ended
        t1 = time.perf_counter()
        assert _wait(lambda: ex.pending == 0, max(10.0, 0.25 * full_s)), (ex.pending, full_s)
        freed = time.perf_counter() - t1
        assert freed < 0.25 * full_s, (freed, full_s)
        small, _ = short_record(24, 5)
        ok = c.post("/v1/models/boucwen/predict", json={"u": small.tolist(), "fs": FS, "mc_paths": 8})
        assert ok.status_code == 200, ok.text[:300]
        text = c.get("/metrics").text
        assert 'gpnarx_requests_timed_out_total{stage="running"} 1.0' in text
        # batch and loops obey the same limit
        rb = c.post("/v1/batch", json={"requests": [{"model": "boucwen", **body}]})
        assert rb.status_code == 504 and rb.json()["field"] == "mc_paths", rb.text[:300]
        assert _wait(lambda: ex.pending == 0, max(10.0, 0.25 * full_s))
        rl = c.post("/v1/models/boucwen/loops", json=body)
        assert rl.status_code == 504, rl.text[:300]


def test_a_linearised_run_past_the_limit_gets_advice_that_applies_to_it():
    """The 504 of a linearised record names u and asks for a shorter record, not for fewer Monte Carlo paths;
    a batch of linearised records names requests."""
    app = create_app(built_registry().root, Settings(workers=1, queue_size=0, request_timeout=0.1))
    body = {"u": multisine(60000, 31).tolist(), "fs": FS, "method": "linear"}  # about a second here
    with LiveServer(app) as srv, httpx.Client(base_url=srv.url, timeout=60) as c:
        r = c.post("/v1/models/boucwen/predict", json=body)
        assert r.status_code == 504, r.text[:300]
        p = r.json()
        assert p["field"] == "u" and "shorter record" in p["detail"] and "mc_paths" not in p["detail"], p
        assert _wait(lambda: app.state.service.executor.pending == 0, 30.0)
        rb = c.post("/v1/batch", json={"requests": [{"model": "boucwen", **body}]})
        assert rb.status_code == 504 and rb.json()["field"] == "requests", rb.text[:300]
        assert "mc_paths" not in rb.json()["detail"]


def test_client_disconnect_frees_the_worker(rate):
    app = create_app(built_registry().root, Settings(workers=1, queue_size=0, request_timeout=0))
    ex = app.state.service.executor
    body, full_s = _long_body(rate)
    with LiveServer(app) as srv:
        with httpx.Client(base_url=srv.url, timeout=httpx.Timeout(60.0, read=1.0)) as c:
            with pytest.raises(httpx.ReadTimeout):  # the client gives up and closes the connection
                c.post("/v1/models/boucwen/predict", json=body)
        t1 = time.perf_counter()
        assert _wait(lambda: ex.pending == 0, max(10.0, 0.25 * full_s)), (ex.pending, full_s)
        assert time.perf_counter() - t1 < 0.25 * full_s
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            small, _ = short_record(24, 5)
            r = c.post("/v1/models/boucwen/predict", json={"u": small.tolist(), "fs": FS, "mc_paths": 8})
            assert r.status_code == 200
            assert "gpnarx_requests_abandoned_total 1.0" in c.get("/metrics").text


def test_queued_request_past_time_limit_is_503(monkeypatch):
    """Deterministic: the job ignores cancellation for 2 s (a long checkpoint interval)."""
    from gpnarx.service import ops

    def stubborn(plan, req, token=None):
        time.sleep(2.0)
        if token is not None:
            token.check()
        return ops.Answer({"model": plan.bundle.name, "version": plan.bundle.version}, 0, None)

    monkeypatch.setattr(ops, "compute", stubborn)
    app = create_app(built_registry().root, Settings(workers=1, queue_size=4, request_timeout=0.5, retry_after=7))
    ex = app.state.service.executor
    small, _ = short_record(16, 5)
    body = {"u": small.tolist(), "fs": FS, "mc_paths": 8}
    with LiveServer(app) as srv:
        out = {}

        def first():
            with httpx.Client(base_url=srv.url, timeout=30) as c:
                out["a"] = c.post("/v1/models/boucwen/predict", json=body)

        t = threading.Thread(target=first)
        t.start()
        try:
            assert _wait(lambda: ex.pending >= 1, 10)
            with httpx.Client(base_url=srv.url, timeout=30) as c:
                r = c.post("/v1/batch", json={"requests": [{"model": "boucwen", **body}]})
                assert r.status_code == 503 and r.headers["Retry-After"] == "7", r.text[:300]
                p = r.json()
                assert r.headers["content-type"].startswith(PROBLEM) and p["limit"] == 0.5
                assert "waited" in p["detail"] and "GPNARX_REQUEST_TIMEOUT" in p["detail"]
                assert ex.pending == 1  # the queued job was dropped at once; only the running one is left
                assert c.get("/health/live").status_code == 200
        finally:
            t.join(timeout=30)
        assert out["a"].status_code == 504
        assert _wait(lambda: ex.pending == 0, 10)
        with httpx.Client(base_url=srv.url, timeout=30) as c:
            text = c.get("/metrics").text
        assert 'gpnarx_requests_timed_out_total{stage="queued"} 1.0' in text
        assert 'gpnarx_requests_timed_out_total{stage="running"} 1.0' in text


def test_fast_requests_unaffected_by_the_limit():
    app = create_app(built_registry().root, Settings(workers=1, queue_size=2, request_timeout=30))
    small, y = short_record(48, 5)
    body = {"u": small.tolist(), "fs": FS, "mc_paths": 16, "seed": 3}
    with LiveServer(app) as srv, httpx.Client(base_url=srv.url, timeout=60) as c:
        r1 = c.post("/v1/models/boucwen/predict", json=body)
        r2 = c.post("/v1/models/boucwen/novelty", json={**body, "y": y.tolist()})
        assert r1.status_code == 200 and r2.status_code == 200
        run = built_registry().model.simulate(small, n_paths=16, seed=3)
        assert np.array_equal(np.asarray(r1.json()["mean"]), run.mean)  # the progress hook changes nothing


def test_a_request_too_slow_even_alone_gets_the_504_advice_at_once():
    """Priced past the limit on an idle service (its size already measured), a request is not refused with a 503
    and a Retry-After that cannot help: it gets the 504's advice and field at once, without computing."""
    from gpnarx.service.worker import JobSize

    app = create_app(built_registry().root, Settings(workers=1, queue_size=2, request_timeout=0.5))
    u = multisine(3000, 7)
    with LiveServer(app) as srv, httpx.Client(base_url=srv.url, timeout=60) as c:
        version = c.get("/v1/models/boucwen").json()["versions"][-1]
        version = version["version"] if isinstance(version, dict) else version
        key = f"boucwen:{version}:predict:linear:numpy"
        app.state.service.executor.model.observe(JobSize.of(key, u.size, 0), 5.0)  # this size took 5 s
        t0 = time.perf_counter()
        r = c.post("/v1/models/boucwen/predict", json={"u": u.tolist(), "fs": FS, "method": "linear"})
        took = time.perf_counter() - t0
        assert r.status_code == 504, r.text[:300]
        p = r.json()
        assert p["field"] == "u" and "on its own" in p["detail"] and "shorter record" in p["detail"], p
        assert "retry-after" not in r.headers and took < 0.5, (r.headers, took)
        assert 'gpnarx_requests_timed_out_total{stage="predicted"} 1.0' in c.get("/metrics").text
