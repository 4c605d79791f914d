"""The model's default propagation: an answer that names no ``method`` uses the trained config's
(``[predict] method``, kept in the manifest), and novelty the one its threshold was calibrated with."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from fastapi.testclient import TestClient
from test_service_support import FS, built_registry, multisine

from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings
from gpnarx.storage.bundle import default_method, derive_bundle
from gpnarx.storage.registry import Registry


@pytest.mark.parametrize("manifest, op, expected", [
    ({}, "predict", "mc"),  # bundles written before the key: the paper's Monte Carlo
    ({"predict": {"method": "linear"}}, "predict", "linear"),
    ({"predict": {"method": "linear"}}, "loops", "linear"),
    ({"predict": {"method": "linear"}, "novelty": {"mc_paths": 256}}, "novelty", "mc"),
    ({"predict": {"method": "mc"}, "novelty": {"mc_paths": 0}}, "novelty", "linear"),
    ({"predict": {"method": "bogus"}}, "predict", "mc"),
])
def test_default_method_from_the_manifest(manifest, op, expected):
    assert default_method(manifest, op) == expected


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    root = tmp_path_factory.mktemp("reg")
    shutil.copytree(built_registry().root, root, dirs_exist_ok=True)
    src = Registry(root).scan().get("plain")
    derive_bundle(src, root, {"predict": {"method": "linear"}}, name="plain-linear")
    return TestClient(create_app(root, Settings(registry=root, workers=1)), raise_server_exceptions=False)


def test_http_answers_use_the_models_default_unless_the_request_names_one(client):
    u = multisine(400, 5).tolist()
    d = client.get("/v1/models/plain-linear").json()
    assert d["default_method"] == {"predict": "linear", "loops": "linear", "novelty": "linear"}
    assert client.get("/v1/models/plain").json()["default_method"]["predict"] == "mc"
    lin = client.post("/v1/models/plain-linear/predict", json={"u": u, "fs": FS}).json()
    assert lin["method"] == "linear" and lin["mc_paths"] == 0
    mc = client.post("/v1/models/plain-linear/predict", json={"u": u, "fs": FS, "method": "mc", "mc_paths": 8}).json()
    assert mc["method"] == "mc" and mc["mc_paths"] == 8
    old = client.post("/v1/models/plain/predict", json={"u": u, "fs": FS, "mc_paths": 8}).json()
    assert old["method"] == "mc"
    assert np.allclose(lin["mean"], client.post("/v1/models/plain/predict",
                                                json={"u": u, "fs": FS, "method": "linear"}).json()["mean"])


def test_cli_predict_uses_the_models_default(tmp_path, capsys):
    from gpnarx.cli.main import main

    rec = tmp_path / "r.npz"
    np.savez(rec, u=multisine(400, 6), fs=FS)
    copy = tmp_path / "reg"
    shutil.copytree(built_registry().root, copy)
    derive_bundle(Registry(copy).scan().get("plain"), copy, {"predict": {"method": "linear"}}, name="plain-linear")
    assert main(["--json", "predict", "--registry", str(copy), "--model", "plain-linear", str(rec)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["method"] == "linear"
    assert main(["--json", "predict", "--registry", str(copy), "--model", "plain-linear", str(rec),
                 "--method", "mc", "--mc", "8"]) == 0
    assert json.loads(capsys.readouterr().out)["method"] == "mc"
