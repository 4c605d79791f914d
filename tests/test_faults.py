"""Faults a plant will meet (issue 33): an emptied store, unauthenticated floods, host-header
redirects, shutdown in the middle of a request, overload and slow clients.

- A registry scan that drops every version (or more than GPNARX_REGISTRY_DROP_SHARE of them) is
  held: the last good registry keeps serving, /health/ready stays 200 and says so, /metrics counts
  it, and the listing is served only once seen on GPNARX_REGISTRY_CONFIRM_SCANS consecutive scans
  or by ``POST /v1/admin/reload?accept_removal=true``.
"""
from __future__ import annotations

import shutil

import pytest
from fastapi.testclient import TestClient
from test_service_support import FS, built_registry, copy_registry, short_record

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


def test_registry_guard_settings_from_env():
    s = Settings.from_env({"GPNARX_REGISTRY_DROP_SHARE": "0.25", "GPNARX_REGISTRY_CONFIRM_SCANS": "5"})
    assert s.registry_drop_share == 0.25 and s.registry_confirm_scans == 5
    with pytest.raises(ValueError, match="GPNARX_REGISTRY_DROP_SHARE must be a number from 0 to 1"):
        Settings.from_env({"GPNARX_REGISTRY_DROP_SHARE": "half"})


def test_emptied_object_store_keeps_serving_from_the_verified_copies(tmp_path, monkeypatch):
    """The issue's outage on fsspec's in-memory store: the bucket is wiped; no model was built before."""
    import fsspec

    from gpnarx.model.bundle import save_bundle

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
