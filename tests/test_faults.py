"""Faults a plant will meet (issue 33): an emptied store, unauthenticated floods, host-header
redirects, shutdown in the middle of a request, overload and slow clients.

- A registry scan that drops every version (or more than GPNARX_REGISTRY_DROP_SHARE of them) is
  held: the last good registry keeps serving, /health/ready stays 200 and says so, /metrics counts
  it, and the listing is served only once seen on GPNARX_REGISTRY_CONFIRM_SCANS consecutive scans
  or by ``POST /v1/admin/reload?accept_removal=true``.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from test_service_support import FS, LiveServer, built_registry, copy_registry, short_record

from gpnarx.client.raw import raw_post
from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings

PROBLEM = "application/problem+json"


def _settings(**kw) -> Settings:
    return Settings(workers=1, queue_size=2, registry_poll=0, **kw)


def _body(n=32):
    u, _ = short_record(n, 5)
    return {"u": u.tolist(), "fs": FS, "mc_paths": 8, "seed": 0}


def _empty(root, aside):
    """Move every model folder of ``root`` to ``aside`` (an emptied store)."""
    aside.mkdir(exist_ok=True)
    for d in list(root.iterdir()):
        shutil.move(str(d), aside / d.name)


def _restore(root, aside):
    for d in list(aside.iterdir()):
        shutil.move(str(d), root / d.name)


# ------------------------------------------------------------------------------------------ emptied store
def test_scan_that_drops_everything_is_held_until_confirmed(tmp_path, caplog):
    root = copy_registry(tmp_path / "reg")
    app = create_app(root, _settings(registry_confirm_scans=3))
    with TestClient(app, raise_server_exceptions=False) as c:
        models = c.get("/health/ready").json()["models"]
        assert models == {"boucwen": ["1", "2"], "plain": ["1"]}
        # a local registry's files are gone with the folder: only models built before serve (an object
        # store's verified local copies stay on disk, so there every version keeps serving)
        assert c.post("/v1/models/boucwen/predict", json=_body()).status_code == 200
        _empty(root, tmp_path / "aside")
        with caplog.at_level("WARNING", logger="gpnarx.service"):
            for scan in (1, 2):
                r = c.post("/v1/admin/reload")
                assert r.status_code == 200, r.text
                d = r.json()
                assert d["held"]["scans"] == scan and d["held"]["needed"] == 3
                assert d["held"]["served"] == 3 and d["held"]["listed"] == 0
                assert d["held"]["dropped"] == ["boucwen:1", "boucwen:2", "plain:1"]
                assert d["models"] == models and d["removed"] == []
                ready = c.get("/health/ready")
                assert ready.status_code == 200, ready.text  # still ready: the last good registry serves
                assert ready.json()["registry_held"]["scans"] == scan
                assert "drops 3 of the 3 served (all)" in ready.json()["registry_held"]["detail"]
                assert c.post("/v1/models/boucwen/predict", json=_body()).status_code == 200
        assert any(rec.levelname == "WARNING" and "keeps serving" in rec.getMessage() for rec in caplog.records)
        text = c.get("/metrics").text
        assert 'gpnarx_registry_scans_total{outcome="held",trigger="reload"} 2.0' in text
        assert "gpnarx_registry_held 1.0" in text
        # the third consecutive scan with the same (empty) listing is served
        r = c.post("/v1/admin/reload")
        assert r.status_code == 200 and "held" not in r.json() and r.json()["bundles"] == 0
        assert r.json()["removed"] == ["boucwen:1", "boucwen:2", "plain:1"]
        assert c.get("/health/ready").status_code == 503
        text = c.get("/metrics").text
        assert "gpnarx_registry_held 0.0" in text and "gpnarx_registry_held_accepted_total 1.0" in text
        assert "gpnarx_registry_versions_removed_total 3.0" in text
        # the store comes back: served at once (an addition is never held)
        _restore(root, tmp_path / "aside")
        r = c.post("/v1/admin/reload")
        assert r.json()["bundles"] == 3 and c.get("/health/ready").status_code == 200


def test_store_that_comes_back_before_confirmation_loses_nothing(tmp_path):
    root = copy_registry(tmp_path / "reg")
    app = create_app(root, _settings(registry_confirm_scans=2))
    with TestClient(app, raise_server_exceptions=False) as c:
        _empty(root, tmp_path / "aside")
        assert c.post("/v1/admin/reload").json()["held"]["scans"] == 1
        _restore(root, tmp_path / "aside")
        r = c.post("/v1/admin/reload").json()
        assert "held" not in r and r["removed"] == [] and r["bundles"] == 3
        assert "registry_held" not in c.get("/health/ready").json()
        # the count starts again: one more empty scan is held, not served
        assert c.post("/v1/models/plain/predict", json=_body()).status_code == 200
        _empty(root, tmp_path / "aside")
        assert c.post("/v1/admin/reload").json()["held"]["scans"] == 1
        assert c.post("/v1/models/plain/predict", json=_body()).status_code == 200


def test_deliberate_removal_and_small_drops(tmp_path):
    root = copy_registry(tmp_path / "reg")
    app = create_app(root, _settings(registry_drop_share=0.5))
    with TestClient(app, raise_server_exceptions=False) as c:
        shutil.rmtree(root / "plain")  # 1 of 3 versions: within the share, served at once
        r = c.post("/v1/admin/reload").json()
        assert "held" not in r and r["removed"] == ["plain:1"]
        shutil.rmtree(root / "boucwen")  # everything left: held ...
        assert c.post("/v1/admin/reload").json()["held"]["dropped"] == ["boucwen:1", "boucwen:2"]
        # ... unless the operator says so
        r = c.post("/v1/admin/reload", params={"accept_removal": "true"})
        assert r.status_code == 200 and "held" not in r.json() and r.json()["bundles"] == 0
        bad = c.post("/v1/admin/reload", params={"accept_removal": "maybe"})
        assert bad.status_code == 422 and bad.json()["field"] == "accept_removal"


def test_poll_holds_an_emptied_store(tmp_path):
    import asyncio

    root = copy_registry(tmp_path / "reg")
    app = create_app(root, _settings(registry_confirm_scans=2))
    state = app.state.service
    _empty(root, tmp_path / "aside")
    held = asyncio.run(state.reload(poll=True))
    assert held["held"]["scans"] == 1 and state.n_bundles() == 3
    done = asyncio.run(state.reload(poll=True))
    assert "held" not in done and state.n_bundles() == 0


@pytest.mark.parametrize("kw, match", [({"registry_drop_share": 1.5}, "registry_drop_share must be a number from 0"),
                                       ({"registry_confirm_scans": 0}, "registry_confirm_scans must be a positive")])
def test_registry_guard_settings_are_checked(kw, match):
    with pytest.raises(ValueError, match=match):
        Settings(**kw)


def test_confirmation_defaults_to_five_minutes_of_polls():
    assert Settings().confirm_scans == 10 and Settings(registry_poll=1).confirm_scans == 300
    assert Settings(registry_poll=600).confirm_scans == 3 and Settings(registry_poll=0).confirm_scans == 3
    assert Settings(registry_poll=1, registry_confirm_scans=2).confirm_scans == 2


def test_registry_guard_settings_from_env():
    s = Settings.from_env({"GPNARX_REGISTRY_DROP_SHARE": "0.25", "GPNARX_REGISTRY_CONFIRM_SCANS": "5"})
    assert s.registry_drop_share == 0.25 and s.registry_confirm_scans == 5
    with pytest.raises(ValueError, match="GPNARX_REGISTRY_DROP_SHARE must be a number from 0 to 1"):
        Settings.from_env({"GPNARX_REGISTRY_DROP_SHARE": "half"})


def test_emptied_object_store_keeps_serving_from_the_verified_copies(tmp_path, monkeypatch):
    """The issue's outage on fsspec's in-memory store: the bucket is wiped; no model was built before."""
    import fsspec

    from gpnarx.storage.bundle import save_bundle

    monkeypatch.setenv("GPNARX_CACHE", str(tmp_path / "cache"))
    url = f"memory://faults-{tmp_path.name}"
    fs = fsspec.filesystem("memory")
    try:
        for v in ("1", "2"):
            save_bundle(built_registry().model, url, "bw", v, fs=FS, units={"u": "N", "y": "m"})
        app = create_app(url, _settings(registry_confirm_scans=3))
        with TestClient(app, raise_server_exceptions=False) as c:
            assert c.get("/health/ready").json()["bundles"] == 2
            fs.rm(f"/faults-{tmp_path.name}", recursive=True)
            for scan in (1, 2):
                assert c.post("/v1/admin/reload").json()["held"]["scans"] == scan
                r = c.post("/v1/models/bw/predict", json=_body())
                assert r.status_code == 200 and r.json()["version"] == "2", r.text[:300]
                assert c.post("/v1/models/bw/versions/1/predict", json=_body()).status_code == 200
                assert c.get("/health/ready").status_code == 200
    finally:
        if fs.exists(f"/faults-{tmp_path.name}"):
            fs.rm(f"/faults-{tmp_path.name}", recursive=True)


# ------------------------------------------------------------------------------------------ reject before reading
def _rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096


def test_missing_key_is_refused_before_the_body_is_read():
    import threading
    import time

    import httpx

    app = create_app(built_registry().root, _settings(api_key="s3cret"))
    junk = b"[" * (30 * 1024 * 1024)  # 30 MiB of invalid JSON, one object shared by every client
    valid = b'{"u": [' + b"1.0," * (7 * 1024 * 1024) + b'1.0], "fs": 750.0}'  # 28 MiB of valid JSON
    with LiveServer(app) as srv, httpx.Client(base_url=srv.url, timeout=60) as c:
        for body in (junk, valid):
            t0 = time.perf_counter()
            r = c.post("/v1/models/boucwen/predict", content=body, headers={"content-type": "application/json"})
            took = time.perf_counter() - t0
            assert r.status_code == 401, r.text[:300]
            assert r.headers["content-type"].startswith(PROBLEM) and r.json()["field"] == "X-API-Key"
            assert took < 5.0, took
        # a wrong key is no better than none; an unknown /v1 path does not reveal itself either
        assert c.post("/v1/batch", content=junk, headers={"X-API-Key": "wrong"}).status_code == 401
        assert c.get("/v1/nothing-here").status_code == 401
        # open paths take no big bodies when a key is set
        r = c.post("/health/live", content=b"x" * (1024 * 1024))
        assert r.status_code == 413 and r.json()["limit"] == 64 * 1024
        # 16 unauthenticated posts at once: the server's memory does not grow by their bodies
        base, peak, stop = _rss(), [0], threading.Event()

        def watch():
            while not stop.is_set():
                peak[0] = max(peak[0], _rss())
                time.sleep(0.01)

        statuses = []

        def flood():  # a raw socket: the client side copies nothing, so the RSS is the server's
            statuses.append(raw_post(srv.port, "/v1/models/boucwen/predict", junk))

        w = threading.Thread(target=watch)
        w.start()
        threads = [threading.Thread(target=flood) for _ in range(16)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=60)
        stop.set()
        w.join()
        assert statuses == [401] * 16
        grew = (peak[0] - base) / 2**20
        assert grew < 64, f"RSS grew by {grew:.0f} MiB under 16 unauthenticated 30 MiB posts"
        # with the key, the same route works
        body = _body()
        assert c.post("/v1/models/boucwen/predict", json=body, headers={"X-API-Key": "s3cret"}).status_code == 200


# ------------------------------------------------------------------------------------------ host header
def test_trailing_slash_is_not_redirected_to_the_client_host():
    c = TestClient(create_app(built_registry().root, _settings()), raise_server_exceptions=False,
                   follow_redirects=False)
    for path in ("/v1/models/", "/v1/models/boucwen/", "/health/live/"):
        r = c.get(path, headers={"Host": "evil.example"})
        assert r.status_code == 404 and "location" not in r.headers, (path, r.status_code, r.headers)
        assert r.headers["content-type"].startswith(PROBLEM)
        assert f"without the trailing slash: {path.rstrip('/')}" in r.json()["detail"]
    assert c.get("/v1/models", headers={"Host": "evil.example"}).status_code == 200
    assert c.get("/v1/models/boucwen").status_code == 200
    assert c.get("/static/ui/app.js").status_code == 200  # the static mount still routes
    keyed = TestClient(create_app(built_registry().root, _settings(api_key="k")), follow_redirects=False)
    assert keyed.get("/v1/models/", headers={"Host": "evil.example"}).status_code == 401


# ------------------------------------------------------------------------------------------ shutdown
def test_drain_window_setting_and_deploy_files_match():
    import yaml

    from gpnarx.service.settings import ENV

    assert Settings().drain_seconds == 130.0 and Settings(request_timeout=300).drain_seconds == 310.0
    assert Settings(drain_timeout=5).drain_seconds == 5.0 and ENV["drain_timeout"] == "GPNARX_DRAIN_TIMEOUT"
    deploy = Path(__file__).resolve().parents[1] / "deploy"
    dep = yaml.safe_load((deploy / "k8s" / "deployment.yaml").read_text())
    spec = dep["spec"]["template"]["spec"]
    env = {e["name"]: e["value"] for e in spec["containers"][0]["env"] if "value" in e}
    drain = Settings.from_env(env).drain_seconds
    assert spec["terminationGracePeriodSeconds"] >= drain + 5, (spec["terminationGracePeriodSeconds"], drain)
    compose = yaml.safe_load((deploy / "compose.yaml").read_text())["services"]["gpnarx"]
    assert float(compose["stop_grace_period"].rstrip("s")) >= drain + 5


def test_request_cut_at_shutdown_is_a_503_problem_with_retry_after(monkeypatch):
    """The drain window ends while a request computes: a problem detail, not uvicorn's text/plain 500."""
    import socket
    import threading
    import time

    import httpx
    import uvicorn

    from gpnarx.service import ops

    started = threading.Event()

    def slow(plan, req, token=None):
        started.set()
        for _ in range(200):  # 10 s unless cancelled
            time.sleep(0.05)
            if token is not None and token.cancelled:
                break
        return ops.Answer({"model": plan.bundle.name, "version": plan.bundle.version}, 0, None)

    monkeypatch.setattr(ops, "compute", slow)
    app = create_app(built_registry().root, _settings(retry_after=4))
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level="critical", timeout_graceful_shutdown=0.5))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    try:
        t0 = time.monotonic()
        while not server.started and time.monotonic() - t0 < 20:
            time.sleep(0.02)
        out = {}

        def call():
            with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30) as c:
                out["r"] = c.post("/v1/models/boucwen/predict", json=_body())

        t = threading.Thread(target=call)
        t.start()
        assert started.wait(20)
        t_stop = time.monotonic()
        server.should_exit = True  # what SIGTERM does
        t.join(timeout=20)
        r = out["r"]
        assert r.status_code == 503, (r.status_code, r.headers.get("content-type"), r.text[:200])
        assert r.headers["content-type"].startswith(PROBLEM) and r.headers["Retry-After"] == "4"
        assert "shutting down" in r.json()["detail"]
        assert time.monotonic() - t_stop < 5.0  # at the end of the drain window, not of the computation
    finally:
        server.should_exit = True
        thread.join(timeout=20)
        sock.close()


# ------------------------------------------------------------------------------------------ slow clients
def _live_server(settings: Settings, **overrides) -> LiveServer:
    """uvicorn with ``gpnarx serve``'s options (``service.server.uvicorn_options``) on a free port."""
    from gpnarx.service.server import uvicorn_options

    app = create_app(built_registry().root, settings)
    return LiveServer(app, log_level="critical", **{**uvicorn_options(settings), **overrides})


def _read_all(s, timeout: float) -> tuple[bytes, float]:
    """Everything the server sends until it closes (or ``timeout``), and when it closed [s]."""
    import time

    t0, data = time.monotonic(), b""
    s.settimeout(0.1)
    while time.monotonic() - t0 < timeout:
        try:
            chunk = s.recv(65536)
        except TimeoutError:
            continue
        except OSError:
            break
        if not chunk:
            return data, time.monotonic() - t0
        data += chunk
    return data, float("inf")


def test_slow_request_heads_are_answered_408_and_closed():
    import socket
    import threading
    import time

    with _live_server(_settings(header_timeout=1.0)) as srv:
        results = []

        def slow_client():
            with socket.create_connection(("127.0.0.1", srv.port), timeout=10) as s:
                t0 = time.monotonic()
                s.sendall(b"GET /health/live HTTP/1.1\r\n")
                closed_at = None
                for i in range(40):  # one header line every 0.2 s: never a complete head
                    time.sleep(0.2)
                    try:
                        s.sendall(f"X-Slow-{i}: 1\r\n".encode())
                    except OSError:
                        closed_at = time.monotonic() - t0
                        break
                data, _ = _read_all(s, 2.0)
                results.append((data, closed_at))

        threads = [threading.Thread(target=slow_client) for _ in range(20)]
        for t in threads:
            t.start()
        # an idle connection that never sends a byte is closed too
        with socket.create_connection(("127.0.0.1", srv.port), timeout=10) as idle:
            data, closed = _read_all(idle, 5.0)
            assert data.startswith(b"HTTP/1.1 408") and closed < 3.0, (data[:100], closed)
        for t in threads:
            t.join(timeout=30)
        assert len(results) == 20
        for data, closed_at in results:
            assert data.startswith(b"HTTP/1.1 408"), data[:200]
            assert b"application/problem+json" in data and b"GPNARX_HEADER_TIMEOUT" in data
            assert closed_at is not None and closed_at < 4.0, closed_at  # 1 s deadline, not 8 s of trickling
        # ordinary clients, keep-alive included, are not affected
        import httpx

        with httpx.Client(base_url=srv.url, timeout=30) as c:
            for _ in range(3):
                assert c.get("/health/live").status_code == 200
                time.sleep(0.4)
            assert c.post("/v1/models/boucwen/predict", json=_body()).status_code == 200


def test_slow_body_is_answered_408_and_closed():
    import socket

    with _live_server(_settings(body_timeout=1.0, header_timeout=5.0)) as srv:
        with socket.create_connection(("127.0.0.1", srv.port), timeout=10) as s:
            s.sendall(b"POST /v1/models/boucwen/predict HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                      b"Content-Length: 100000\r\n\r\n{\"u\": [1.0, ")
            data, closed = _read_all(s, 6.0)
        assert data.startswith(b"HTTP/1.1 408"), data[:200]
        assert b'"field":"body"' in data.replace(b" ", b"") and b"GPNARX_BODY_TIMEOUT" in data
        assert closed < 4.0, closed


def test_connection_limit_and_head_size():
    import socket

    import httpx

    with _live_server(_settings(max_connections=3, header_timeout=30.0, retry_after=3)) as srv:
        held = [socket.create_connection(("127.0.0.1", srv.port), timeout=10) for _ in range(3)]
        try:
            import time

            time.sleep(0.3)
            with socket.create_connection(("127.0.0.1", srv.port), timeout=10) as extra:
                data, closed = _read_all(extra, 3.0)
            assert data.startswith(b"HTTP/1.1 503") and b"retry-after: 3" in data.lower(), data[:300]
            assert b"GPNARX_MAX_CONNECTIONS" in data and closed < 3.0
        finally:
            for s in held:
                s.close()
        time.sleep(0.3)
        with httpx.Client(base_url=srv.url, timeout=30) as c:
            assert c.get("/health/live").status_code == 200
        with socket.create_connection(("127.0.0.1", srv.port), timeout=10) as s:
            s.sendall(b"GET /health/live HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * (32 * 1024))
            data, closed = _read_all(s, 3.0)
        assert data.startswith(b"HTTP/1.1 400"), data[:200]  # past GPNARX_MAX_HEADER_BYTES (16 KiB), incomplete


def test_server_settings_from_env():
    from gpnarx.service.server import uvicorn_options

    s = Settings.from_env({"GPNARX_HEADER_TIMEOUT": "2.5", "GPNARX_BODY_TIMEOUT": "30", "GPNARX_MAX_CONNECTIONS": "64",
                           "GPNARX_KEEP_ALIVE_TIMEOUT": "7", "GPNARX_MAX_HEADER_BYTES": "32768"})
    opts = uvicorn_options(s)
    assert opts["http"].header_timeout == 2.5 and opts["http"].max_connections == 64
    assert opts["timeout_keep_alive"] == 7 and opts["h11_max_incomplete_event_size"] == 32768
    assert s.body_timeout == 30 and opts["timeout_graceful_shutdown"] == 130.0
    with pytest.raises(ValueError, match="max_header_bytes must be an integer of at least 1024"):
        Settings(max_header_bytes=10)


# ------------------------------------------------------------------------------------------ overload
def test_job_that_cannot_start_in_time_is_refused_at_once():
    import asyncio
    import threading
    import time

    from gpnarx.service.worker import BoundedExecutor, JobSize, WontStart

    async def scenario():
        ex = BoundedExecutor(1, 4)
        assert ex.wait_estimate() == 0.0  # a worker is free
        await ex.run(time.sleep, 0.2, work=1000)  # measured: about 0.2 ms per work unit
        await ex.run(time.sleep, 0.4, work=2000)
        assert 0.7 < ex.model.estimate(JobSize.work(4000)) < 2.0  # about 0.8 s: 0.2 ms per unit, timer noise aside
        release = threading.Event()
        running = asyncio.ensure_future(ex.run(release.wait, 10, work=5000))  # about 1 s by the measure
        await asyncio.sleep(0.1)
        assert ex.wait_estimate() > 0.6
        t0 = time.perf_counter()
        try:
            await ex.run(time.sleep, 0, timeout=0.5, work=10)
            raise AssertionError("not refused")
        except WontStart as exc:
            assert exc.timeout == 0.5 and exc.wait > 0.5 and exc.retry_after > 0
        assert time.perf_counter() - t0 < 0.1  # at once, not at its deadline
        assert ex.pending == 1  # the refused job took no slot
        release.set()
        await running

    asyncio.run(scenario())


def test_queued_job_is_refused_once_the_estimate_shows_it_cannot_start():
    """No job has finished yet when B queues; A's progress gives the rate; B is dropped long before its deadline."""
    import asyncio
    import threading
    import time

    from gpnarx.service.worker import BoundedExecutor, CancelToken, WontStart

    async def scenario():
        ex = BoundedExecutor(1, 4)
        token, release = CancelToken(), threading.Event()

        def long_job():
            time.sleep(0.5)
            token.progress(5, 100)  # 5 % in 0.5 s: about 10 s for the whole job
            release.wait(30)

        a = asyncio.ensure_future(ex.run(long_job, work=10000, token=token))
        await asyncio.sleep(0.05)
        t0 = time.perf_counter()
        try:
            await ex.run(time.sleep, 0, timeout=8.0, work=100)
            raise AssertionError("not refused")
        except WontStart as exc:
            assert exc.wait > 8.0
        took = time.perf_counter() - t0
        assert took < 3.0, took  # refused within a slice of the estimate, not at the 8 s deadline
        assert ex.pending == 1
        release.set()
        await a

    asyncio.run(scenario())


def test_busy_answer_before_the_body_is_read_with_retry_after_from_the_queue():
    import time

    from gpnarx.service.worker import JobSize, _Job

    app = create_app(built_registry().root, Settings(workers=1, queue_size=0, retry_after=2, registry_poll=0))
    state = app.state.service
    ex = state.executor
    with TestClient(app, raise_server_exceptions=False) as c:
        assert state.retry_after() == 2  # idle: the configured floor
        running = _Job(JobSize.work(1000))  # one job of about 10 s running
        ex.model.observe(JobSize.work(1000), 10.0)
        running.started = time.monotonic()
        ex._jobs[0] = running
        r = c.post("/v1/models/boucwen/predict", content=b"{not json", headers={"content-type": "application/json"})
        assert r.status_code == 503, r.text  # not 400: the body was never parsed
        assert r.headers["Retry-After"] == "10" and r.headers["content-type"].startswith(PROBLEM)
        assert "retry after 10 s" in r.json()["detail"]
        assert c.post("/v1/batch", content=b"{").status_code == 503
        assert c.get("/health/live").status_code == 200 and c.get("/v1/models").status_code == 200
        assert "gpnarx_requests_shed_total 2.0" in c.get("/metrics").text
        ex._jobs.clear()
        assert c.post("/v1/models/boucwen/predict", json=_body()).status_code == 200


# ------------------------------------------------------------------------------------------ leftovers
_KILLED_WRITER = """
import sys, time
from pathlib import Path
from gpnarx.storage import bundle

def fill(tmp, version):
    (tmp / "theta.npy").write_bytes(b"partial")
    print(tmp, flush=True)
    time.sleep(120)

bundle._write_new_version(Path(sys.argv[1]), "boucwen", None, fill)
"""


def test_killed_write_leftover_is_removed_at_start_and_by_a_scan(tmp_path, caplog):
    import os
    import signal
    import subprocess
    import sys

    from gpnarx.storage.bundle import writer_tag

    root = copy_registry(tmp_path / "reg")

    def killed_write() -> Path:
        p = subprocess.Popen([sys.executable, "-c", _KILLED_WRITER, str(root)], stdout=subprocess.PIPE, text=True)
        tmp = Path(p.stdout.readline().strip())
        assert tmp.is_dir() and tmp.name.startswith(".tmp-3-w")
        os.kill(p.pid, signal.SIGKILL)  # a calibrate killed inside its publish
        p.wait()
        return tmp

    first = killed_write()
    alive = root / "boucwen" / f".tmp-9-{writer_tag()}-alive"  # a write in progress in this living process: kept
    alive.mkdir()
    unknown = root / "boucwen" / ".tmp-8-unknown"  # no writer file, fresh: kept for an hour
    unknown.mkdir()
    with caplog.at_level("WARNING", logger="gpnarx.service"):
        app = create_app(root, _settings())
    assert not first.exists() and alive.is_dir() and unknown.is_dir()
    assert any("killed write" in r.getMessage() and first.name in r.getMessage() for r in caplog.records)
    with TestClient(app, raise_server_exceptions=False) as c:
        assert "gpnarx_registry_leftovers_removed_total 1.0" in c.get("/metrics").text
        second = killed_write()
        r = c.post("/v1/admin/reload")
        assert r.status_code == 200 and not second.exists() and alive.is_dir()
        text = c.get("/metrics").text
        assert "gpnarx_registry_leftovers_removed_total 2.0" in text
        assert 'gpnarx_registry_scans_total{outcome="unchanged",trigger="reload"} 1.0' in text
        assert r.json()["models"] == {"boucwen": ["1", "2"], "plain": ["1"]}  # nothing half-written listed


def test_object_store_leftovers_are_removed_by_age_at_start_and_scan(tmp_path, monkeypatch):
    """A killed publish on an object store (a version's objects without its manifest) is removed by a
    server's start or scan once its newest object is GPNARX_REGISTRY_LEFTOVER_AGE old; a live writer's
    fresh objects, and objects that are no version, are kept."""
    import time

    import fsspec

    from gpnarx.storage.bundle import save_bundle

    monkeypatch.setenv("GPNARX_CACHE", str(tmp_path / "cache"))
    top = f"/left-{tmp_path.name}"
    url, fs = f"memory:/{top}", fsspec.filesystem("memory")
    try:
        save_bundle(built_registry().model, url, "bw", "1", fs=FS, units={"u": "N", "y": "m"})
        fs.pipe(f"{top}/bw/2/theta.npy", b"partial")  # a calibrate killed inside its publish
        fs.pipe(f"{top}/bw/2/report/index.html", b"partial")
        fs.pipe(f"{top}/bw/notes/readme.txt", b"not a version: never touched")
        app = create_app(url, _settings(registry_leftover_age=1))
        assert fs.exists(f"{top}/bw/2/theta.npy")  # fresh at start: could be a live writer's
        time.sleep(1.2)
        fs.pipe(f"{top}/bw/3/theta.npy", b"a live writer's first object")
        with TestClient(app, raise_server_exceptions=False) as c:
            r = c.post("/v1/admin/reload")
            assert r.status_code == 200 and r.json()["models"] == {"bw": ["1"]}
            assert not fs.exists(f"{top}/bw/2/theta.npy") and not fs.exists(f"{top}/bw/2/report/index.html")
            assert fs.exists(f"{top}/bw/3/theta.npy") and fs.exists(f"{top}/bw/notes/readme.txt")
            assert "gpnarx_registry_leftovers_removed_total 1.0" in c.get("/metrics").text
        time.sleep(1.2)
        create_app(url, _settings(registry_leftover_age=1))  # at start too, once old enough
        assert not fs.exists(f"{top}/bw/3/theta.npy") and fs.exists(f"{top}/bw/1/manifest.json")
        create_app(url, _settings(registry_leftover_age=0))  # 0: never by age
    finally:
        if fs.exists(top):
            fs.rm(top, recursive=True)


def test_publisher_whose_objects_were_removed_does_not_publish(tmp_path, monkeypatch):
    """A writer slower than the leftover age whose uploads a scan removed fails before its manifest."""
    import fsspec

    from gpnarx.storage import bundle
    from gpnarx.storage.remote import RemoteStore

    top = f"/slow-{tmp_path.name}"
    url, fs = f"memory:/{top}", fsspec.filesystem("memory")
    real = RemoteStore.listing

    def listing(self, under=""):  # a scan removed the first uploaded object meanwhile
        out = real(self, under)
        if under == "bw/1" and out:
            first = sorted(out)[0]
            self.remove([first])
            out.pop(first)
        return out

    monkeypatch.setattr(RemoteStore, "listing", listing)
    try:
        with pytest.raises(bundle.BundleError, match="removed meanwhile"):
            bundle.save_bundle(built_registry().model, url, "bw", "1", fs=FS, units={"u": "N", "y": "m"})
        assert not fs.exists(f"{top}/bw/1/manifest.json")
    finally:
        if fs.exists(top):
            fs.rm(top, recursive=True)


def test_local_leftover_of_another_host_is_removed_once_old(tmp_path):
    import os
    import time

    root = copy_registry(tmp_path / "reg")
    other = root / "boucwen" / ".tmp-7-wdeadbeefp1s1-x"  # another host's writer: judged by age only
    other.mkdir()
    create_app(root, _settings())
    assert other.is_dir()
    old = time.time() - 601
    os.utime(other, (old, old))
    create_app(root, _settings(registry_leftover_age=0))  # 0: never by age
    assert other.is_dir()
    create_app(root, _settings())  # the default 600 s
    assert not other.exists()


# ------------------------------------------------------------------------------------------ chaos on moto S3
def test_chaos_two_replicas_on_moto_emptied_and_killed_store(tmp_path, monkeypatch):
    """Two replicas (real uvicorn servers with ``gpnarx serve``'s options, each with its own cache, an API
    key) on one moto S3 registry. The bucket is emptied; unauthenticated 8 MiB bodies flood one replica;
    the other is SIGTERMed in the middle of a long request; then the store is killed. No predict or
    readiness answer is anything but 200, the long request finishes within the drain window, and the
    flood leaves the process's memory where it was."""
    import threading
    import time

    import httpx

    pytest.importorskip("s3fs")
    server_mod = pytest.importorskip("moto.server")
    import s3fs

    from gpnarx.service import ops
    from gpnarx.service.server import uvicorn_options
    from gpnarx.storage.bundle import save_bundle

    real_compute = ops.compute

    def compute(plan, req, token=None):  # a long request: the one with seed 99
        if getattr(req, "seed", None) == 99:
            time.sleep(2.0)
        return real_compute(plan, req, token)

    monkeypatch.setattr(ops, "compute", compute)
    server = server_mod.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    for k, v in {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing",
                 "AWS_DEFAULT_REGION": "us-east-1", "AWS_ENDPOINT_URL": f"http://{host}:{port}"}.items():
        monkeypatch.setenv(k, v)
    for k in ("AWS_PROFILE", "AWS_SESSION_TOKEN", "AWS_ENDPOINT_URL_S3", "GPNARX_STORAGE_OPTIONS"):
        monkeypatch.delenv(k, raising=False)
    s3fs.S3FileSystem.clear_instance_cache()
    fs = s3fs.S3FileSystem()
    url = "s3://faults/plant"
    key = {"X-API-Key": "k3y"}
    stopped, replicas = False, []
    try:
        fs.mkdir("faults")
        for v in ("1", "2"):
            save_bundle(built_registry().model, url, "bw", v, fs=FS, units={"u": "N", "y": "m"})
        settings = _settings(registry_confirm_scans=3, api_key="k3y", drain_timeout=10)
        for i in range(2):
            monkeypatch.setenv("GPNARX_CACHE", str(tmp_path / f"cache-{i}"))
            replicas.append(LiveServer(create_app(url, settings), **uvicorn_options(settings)).__enter__())
        clients = [httpx.Client(base_url=r.url, timeout=30, headers=key) for r in replicas]
        statuses = []

        def traffic(live=(0, 1)):
            for i in live:
                statuses.append(clients[i].post("/v1/models/bw/predict", json=_body()).status_code)
                statuses.append(clients[i].get("/health/ready").status_code)

        traffic()
        fs.rm("faults/plant", recursive=True)  # the store comes back empty
        s3fs.S3FileSystem.clear_instance_cache()
        for _ in range(2):
            for c in clients:
                assert c.post("/v1/admin/reload").json()["held"]["listed"] == 0
            traffic()
        # an unauthenticated flood on replica 0 while both serve
        junk, flood = b"[" * (8 * 1024 * 1024), []
        base = _rss()
        threads = [threading.Thread(target=lambda: flood.append(raw_post(replicas[0].port, "/v1/models/bw/predict",
                                                                          junk))) for _ in range(16)]
        for t in threads:
            t.start()
        traffic()
        for t in threads:
            t.join(timeout=60)
        assert flood == [401] * 16 and (_rss() - base) / 2**20 < 64
        # a rolling update: replica 1 gets SIGTERM while a long request runs on it; replica 0 keeps serving
        long = {}
        t = threading.Thread(target=lambda: long.update(r=clients[1].post("/v1/models/bw/predict",
                                                                          json={**_body(), "seed": 99})))
        t.start()
        time.sleep(0.5)
        t_stop = time.monotonic()
        replicas[1].server.should_exit = True  # what SIGTERM does
        traffic(live=(0,))
        t.join(timeout=30)
        assert long["r"].status_code == 200 and time.monotonic() - t_stop < 10  # finished in the drain window
        replicas[1].thread.join(timeout=20)
        assert not replicas[1].thread.is_alive()
        server.stop()  # the store is gone altogether
        stopped = True
        monkeypatch.setenv("AWS_MAX_ATTEMPTS", "1")
        assert clients[0].post("/v1/admin/reload").status_code == 503  # says so, and keeps serving
        traffic(live=(0,))
        assert statuses and all(s == 200 for s in statuses), statuses
        ready = clients[0].get("/health/ready").json()
        assert ready["bundles"] == 2 and ready["registry_held"]["scans"] == 2
        for c in clients:
            c.close()
    finally:
        for r in replicas:
            r.__exit__(None, None, None)
        if not stopped:
            server.stop()
        s3fs.S3FileSystem.clear_instance_cache()
