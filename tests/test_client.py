"""gpnarx.client against a live uvicorn server (and a mock transport for the retry rules); the README's
client example runs as written, against the live server."""
from __future__ import annotations

import asyncio
import re
from pathlib import Path

import httpx
import numpy as np
import pytest
from test_service_support import FS, LiveServer, built_registry, copy_registry, multisine, noisy, simulate

from gpnarx.client import (
    AsyncClient,
    Client,
    GpnarxError,
    InvalidRequest,
    NotFound,
    Overloaded,
    TooLarge,
    Unauthorized,
    error_for,
)
from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def registry(tmp_path_factory):
    from gpnarx.storage.bundle import save_bundle

    root = copy_registry(tmp_path_factory.mktemp("client") / "reg")
    # the README's example calls the default registry's model name
    save_bundle(built_registry().model, root, "bouc-wen", "1", fs=FS, units={"u": "N", "y": "m"},
                physics={"mass": 2.0, "input_gain": 1.0, "output": "displacement"})
    return root


@pytest.fixture(scope="module")
def server(registry):
    with LiveServer(create_app(registry, Settings(workers=2, queue_size=8, max_samples=4096))) as srv:
        yield srv


@pytest.fixture(scope="module")
def client(server):
    with Client(server.url) as c:
        yield c


def record(n=512, seed=3):
    u = multisine(n, seed)
    return u, noisy(simulate(u), 40 + seed)


def test_readme_example_runs_against_a_live_server(server, tmp_path, monkeypatch, capsys):
    readme = (ROOT / "README.md").read_text()
    m = re.search(r"<!-- client-example[^>]*-->\s*```python\n(.*?)```", readme, re.S)
    assert m, "README.md has no client example block"
    code = m.group(1)
    # the address and key follow the environment (the server's GPNARX_API_KEY), not a port typed into the code
    assert 'os.environ.get("GPNARX_URL", "http://127.0.0.1:8000")' in code and code.count(":8000") == 1
    assert 'api_key=os.environ.get("GPNARX_API_KEY")' in code
    u, y = record(700, 4)
    np.savez(tmp_path / "sine-50N.npz", u=u, y=y, fs=FS)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("GPNARX_URL", server.url)
    monkeypatch.delenv("GPNARX_API_KEY", raising=False)
    exec(compile(code, "README.md", "exec"), {})
    out = capsys.readouterr().out.splitlines()
    assert "bouc-wen" in out[0]
    shape, dtype, fit, coverage = out[1].split()[:4]
    assert shape == "(700,)" and dtype == "float64" and float(fit) > 50 and 0 <= float(coverage) <= 100
    assert out[2].startswith("422 fs ") and "750" in out[2]


def test_predict_arrays_in_and_out_both_wires(server, client):
    u, y = record()
    p = client.predict("boucwen", u=u, fs=FS, y=y, mc_paths=16, seed=2)
    for k in ("mean", "lower", "upper", "std"):
        assert isinstance(getattr(p, k), np.ndarray) and p[k].dtype == np.float64 and p[k].shape == u.shape
    assert np.all(p.lower <= p.mean) and np.all(p.mean <= p.upper)
    assert isinstance(p.fit, float) and isinstance(p.out_of_range, list)
    with Client(server.url, wire="json") as cj:
        q = cj.predict("boucwen", u=u.tolist(), fs=FS, y=y, mc_paths=16, seed=2)
    np.testing.assert_array_equal(p.mean, q.mean)
    np.testing.assert_array_equal(p.std, q.std)
    assert p.fit == pytest.approx(q.fit) and p.out_of_range == q.out_of_range
    v = client.predict("boucwen", u=u, fs=FS, version="1", method="linear")
    assert v.method == "linear" and v.mean.shape == u.shape


def test_models_model_report_loops_novelty(client):
    names = [m["name"] for m in client.models()]
    assert {"boucwen", "plain", "bouc-wen"} <= set(names)
    assert client.model("boucwen", "1")["version"] == "1"
    u, y = record(640, 7)
    loops = client.loops("boucwen", u=u, fs=FS, mc_paths=8)
    assert isinstance(loops.predicted["x"], np.ndarray) and loops.predicted["force"].shape == loops.predicted["x"].shape
    nov = client.novelty("boucwen", u=u, fs=FS, y=y, mc_paths=8)
    assert nov.verdict in ("healthy", "novel", "unjudged") and nov.score >= 0
    with pytest.raises(NotFound) as e:
        client.report("boucwen", "1")
    assert e.value.status == 404


def test_typed_problems(client):
    u, _ = record(64)
    with pytest.raises(NotFound) as e:
        client.predict("nosuch", u=u, fs=FS)
    assert e.value.field == "name" and "nosuch" in e.value.detail
    with pytest.raises(InvalidRequest) as e:
        client.predict("boucwen", u=u, fs=FS, mc_paths=0)
    assert e.value.field == "mc_paths"
    with pytest.raises(TooLarge) as e:
        client.predict("boucwen", u=np.zeros(5000), fs=FS)
    assert e.value.field == "u" and e.value.problem["limit"] == 4096
    assert isinstance(e.value, GpnarxError)
    with pytest.raises(TypeError):
        asyncio.run(AsyncClient("http://x").predict("m", u=u, fs=FS, colour="red"))


def test_batch_slots_answer_or_fail_alone(client):
    u, y = record(256, 9)
    res = client.batch([{"model": "boucwen", "u": u, "fs": FS, "mc_paths": 8},
                        {"model": "nosuch", "u": u, "fs": FS},
                        {"model": "boucwen", "operation": "novelty", "u": u, "y": y, "fs": FS, "mc_paths": 8}])
    assert isinstance(res[0].mean, np.ndarray) and res[0].mean.shape == u.shape
    assert isinstance(res[1], NotFound) and res[1].status == 404
    assert res[2].verdict in ("healthy", "novel", "unjudged")


def test_api_key(registry):
    with LiveServer(create_app(registry, Settings(workers=1, queue_size=2, api_key="s3cret"))) as srv:
        with Client(srv.url) as c, pytest.raises(Unauthorized):
            c.models()
        with Client(srv.url, api_key="s3cret") as c:
            assert c.models()


def test_async_client(server):
    u, y = record(300, 5)

    async def go():
        async with AsyncClient(server.url) as c:
            models, p = await asyncio.gather(c.models(), c.predict("boucwen", u=u, fs=FS, y=y, mc_paths=8))
            try:
                await c.predict("nosuch", u=u, fs=FS)
            except NotFound as exc:
                return models, p, exc
        return models, p, None

    models, p, exc = asyncio.run(go())
    assert any(m["name"] == "boucwen" for m in models)
    assert isinstance(p.upper, np.ndarray) and p.upper.shape == u.shape and isinstance(exc, NotFound)


def _overloaded_then_ok(n_busy: int, calls: list):
    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(request)
        if len(calls) <= n_busy:
            problem = {"type": "https://gpnarx.dev/problems/overloaded", "title": "Service Unavailable",
                       "status": 503, "detail": "the work queue is full", "field": None}
            return httpx.Response(503, headers={"Retry-After": "0.01"}, json=problem)
        return httpx.Response(200, json={"models": [{"name": "m"}]})
    return handler


def test_503_is_retried_after_retry_after():
    calls: list = []
    with Client("http://svc", transport=httpx.MockTransport(_overloaded_then_ok(2, calls)), retries=3) as c:
        assert c.models() == [{"name": "m"}]
    assert len(calls) == 3
    calls.clear()
    with Client("http://svc", transport=httpx.MockTransport(_overloaded_then_ok(5, calls)), retries=1) as c:
        with pytest.raises(Overloaded) as e:
            c.models()
    assert len(calls) == 2 and e.value.retry_after == pytest.approx(0.01)

    async def go():
        acalls: list = []
        async with AsyncClient("http://svc", transport=httpx.MockTransport(_overloaded_then_ok(1, acalls))) as c:
            return await c.models(), len(acalls)

    assert asyncio.run(go()) == ([{"name": "m"}], 2)


def test_error_for_unknown_problem_types():
    assert type(error_for({"type": "about:blank", "status": 418, "detail": "x"})) is GpnarxError
    assert type(error_for({"type": "about:blank", "status": 404, "detail": "x"})) is NotFound


def test_stream_state_through_the_client(client):
    u, _ = record(400, 8)
    whole = client.predict("boucwen", u=u, fs=FS, method="linear")
    first = client.predict("boucwen", u=u[:200], fs=FS, method="linear", return_state=True)
    assert isinstance(first.state, str) and first.state
    second = client.predict("boucwen", u=u[200:], fs=FS, method="linear", state=first.state)
    np.testing.assert_allclose(np.concatenate([first.mean, second.mean]), whole.mean, rtol=1e-9, atol=1e-12)


def test_every_problem_type_the_service_uses_has_its_own_exception_class():
    """A problem type added to service.problems.SLUGS without a client class would fall back to GpnarxError."""
    from gpnarx.client.core import BY_TYPE
    from gpnarx.service.problems import SLUGS, TYPE_BASE

    assert set(BY_TYPE) == {TYPE_BASE + slug for slug in SLUGS.values()}
    assert len(set(BY_TYPE.values())) == len(BY_TYPE)
    for status, slug in SLUGS.items():
        cls = BY_TYPE[TYPE_BASE + slug]
        assert cls is not GpnarxError and issubclass(cls, GpnarxError) and cls.status == status
        assert type(error_for({"type": TYPE_BASE + slug, "status": status, "detail": "x"})) is cls


@pytest.mark.parametrize("wire", ["npz", "json"])
def test_horizon_and_gaps_through_the_client(server, wire):
    """``horizon`` and NaN gaps go out on either wire; the answer's gap comes back as NaN, with ``gaps``."""
    u, y = record()
    ug = u.copy()
    ug[100:120] = np.nan
    with Client(server.url, wire=wire) as c:
        k = c.predict("boucwen", u=u, fs=FS, y=y, method="linear", horizon=8)
        g = c.predict("boucwen", u=ug, fs=FS, y=y, method="linear")
        free = c.predict("boucwen", u=u, fs=FS, y=y, method="linear")
    assert k.horizon == 8 and k.mean.dtype == np.float64 and k.fit > free.fit
    assert "horizon" not in free and "gaps" not in free
    assert g.gaps == [{"start": 100, "end": 120, "start_s": 100 / FS, "end_s": 120 / FS}]
    assert np.isnan(g.mean[100:120]).all() and np.isfinite(g.mean[:100]).all() and np.isfinite(g.std[120:]).all()
