"""Large request bodies are parsed and validated off the event loop (``service.bodies``), by the record
routes and by the batch route through the same ``off_loop``; small ones inline. The answers are the
same either way."""
from __future__ import annotations

import asyncio

import pytest
from fastapi.testclient import TestClient
from test_service_support import FS, built_registry, short_record

from gpnarx.service import bodies
from gpnarx.service.app import create_app
from gpnarx.service.routers import batch as batch_mod
from gpnarx.service.routers import predict as predict_mod
from gpnarx.service.settings import Settings


def _on_loop() -> bool:
    try:
        asyncio.get_running_loop()
        return True
    except RuntimeError:
        return False


@pytest.fixture(scope="module")
def client():
    app = create_app(built_registry().root, Settings(workers=1, queue_size=4, registry_poll=0))
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


def _record(n: int) -> dict:
    u, _ = short_record(n, 5)
    return {"u": u.tolist(), "fs": FS, "method": "linear"}


def _spy(monkeypatch, module, name: str) -> list:
    """Record, for each call of ``module.name``, whether it ran on the event loop's thread."""
    seen, real = [], getattr(module, name)

    def spy(*args):
        seen.append(_on_loop())
        return real(*args)

    monkeypatch.setattr(module, name, spy)
    return seen


def test_off_loop_runs_large_bodies_on_a_thread_small_ones_inline():
    async def main():
        small = await bodies.off_loop(bodies.OFF_LOOP_BYTES - 1, _on_loop)
        large = await bodies.off_loop(bodies.OFF_LOOP_BYTES, _on_loop)
        return small, large

    assert asyncio.run(main()) == (True, False)


def test_large_batch_is_parsed_and_validated_off_the_loop(client, monkeypatch):
    seen = _spy(monkeypatch, batch_mod, "read_items")
    small = {"requests": [{"model": "boucwen", **_record(64)}]}
    big_rec = _record(4000)  # about 80 kB of JSON: over OFF_LOOP_BYTES
    big = {"requests": [{"model": "boucwen", **big_rec}, {"model": "boucwen", "u": "not a list", "fs": FS}]}
    r_small = client.post("/v1/batch", json=small)
    r_big = client.post("/v1/batch", json=big)
    assert seen == [True, False], seen  # the small body inline, the large one on a worker thread
    assert r_small.status_code == 200 and "mean" in r_small.json()["results"][0]
    assert r_big.status_code == 200, r_big.text[:300]
    res = r_big.json()["results"]
    # each record answered or refused on its own, as before: the valid one equals the single route's answer
    single = client.post("/v1/models/boucwen/predict", json=big_rec).json()
    assert res[0]["mean"] == single["mean"]
    assert res[1]["status"] == 422 and res[1]["field"].startswith("requests.1.u")


def test_large_batch_errors_are_the_same_problems(client):
    pad = " " * bodies.OFF_LOOP_BYTES  # whitespace makes the body large without changing its meaning
    cases = [(b"[" + pad.encode(), 400, "body"), (('{"requests": []}' + pad).encode(), 422, "requests"),
             (('{"requests": [], "x": 1}' + pad).encode(), 422, "x")]
    for raw, status, field in cases:
        r = client.post("/v1/batch", content=raw, headers={"content-type": "application/json"})
        assert r.status_code == status and r.json()["field"] == field, (status, r.text[:200])
        small = client.post("/v1/batch", content=raw[:-len(pad)] if raw.endswith(pad.encode()) else raw[:1],
                            headers={"content-type": "application/json"})
        assert small.json()["status"] == status and small.json()["field"] == field


def test_large_record_is_validated_off_the_loop(client, monkeypatch):
    seen = _spy(monkeypatch, predict_mod, "parse_or_none")
    r = client.post("/v1/models/boucwen/predict", json=_record(4000))
    assert r.status_code == 200 and seen == [False]
    r = client.post("/v1/models/boucwen/predict", json=_record(64))  # small: FastAPI's own way, no parse_or_none
    assert r.status_code == 200 and seen == [False]
