"""k-step-ahead prediction (``horizon``) and records with gaps (null samples) over HTTP, in a batch, through the
client's arguments, the NPZ body and the CLI: one operations layer, the same numbers as the model's."""
from __future__ import annotations

import io
import json

import numpy as np
import pytest
from fastapi.testclient import TestClient
from test_service_support import FS, built_registry, short_record

from gpnarx.cli.main import main
from gpnarx.model.metrics import fit_percent
from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings
from gpnarx.storage.bundle import load_bundle

PROBLEM = "application/problem+json"
URL = "/v1/models/boucwen/predict"


@pytest.fixture(scope="module")
def registry():
    return built_registry().root


@pytest.fixture(scope="module")
def client(registry):
    return TestClient(create_app(registry, Settings(workers=1, queue_size=8)), raise_server_exceptions=False)


@pytest.fixture(scope="module")
def model(registry):
    versions = sorted((registry / "boucwen").iterdir(), key=lambda p: p.name)
    return load_bundle(versions[-1]).model


@pytest.fixture(scope="module")
def rec():
    return short_record(400, 7)


def _problem(r, status, field):
    assert r.status_code == status, r.text[:400]
    assert r.headers["content-type"].startswith(PROBLEM)
    p = r.json()
    assert p["field"] == field and p["detail"], p
    return p


def test_horizon_answer_is_the_models_k_step_prediction(client, model, rec):
    u, y = rec
    body = {"u": u.tolist(), "y": y.tolist(), "fs": FS, "method": "linear", "horizon": 16}
    r = client.post(URL, json=body)
    assert r.status_code == 200, r.text[:400]
    a = r.json()
    assert a["horizon"] == 16 and "gaps" not in a
    run = model.simulate(u, y=y, horizon=16, method="linear")
    np.testing.assert_allclose(a["mean"], run.mean, rtol=1e-12, atol=0)
    np.testing.assert_allclose(a["upper"], run.upper, rtol=1e-12, atol=0)
    assert a["fit"] == pytest.approx(fit_percent(y, run.mean), rel=1e-12)
    free = client.post(URL, json={**body, "horizon": None}).json()  # no horizon: the answer as before
    assert "horizon" not in free and free["fit"] < a["fit"]
    # Monte Carlo: the same request, the same answer
    mc = {**body, "method": "mc", "mc_paths": 32, "seed": 4}
    one, two = client.post(URL, json=mc).json(), client.post(URL, json=mc).json()
    assert one["horizon"] == 16 and one["mean"] == two["mean"] and one["mc_paths"] == 32


def test_horizon_in_a_batch_and_in_an_npz_query(client, rec):
    u, y = rec
    item = {"model": "boucwen", "u": u.tolist(), "y": y.tolist(), "fs": FS, "method": "linear"}
    r = client.post("/v1/batch", json={"requests": [{**item, "horizon": 8}, {**item, "horizon": 0}, item]})
    res = r.json()["results"]
    assert res[0]["horizon"] == 8 and "horizon" not in res[2]
    assert res[1]["status"] == 422 and res[1]["field"] == "requests.1.horizon", res[1]
    buf = io.BytesIO()
    np.savez(buf, u=u, y=y, fs=FS)
    npz = client.post(URL + "?method=linear&horizon=8", content=buf.getvalue(),
                      headers={"content-type": "application/x-npz"})
    assert npz.status_code == 200, npz.text[:300]
    assert npz.json()["horizon"] == 8 and npz.json()["mean"] == res[0]["mean"]


@pytest.mark.parametrize("extra, field, needle", [
    ({"y": None}, "y", "send the record's measured output y"),
    ({"horizon": 0}, "horizon", None),
    ({"horizon": 2.5}, "horizon", None),
    ({"return_state": True}, "horizon", "stream"),
    ({"start": "measured"}, "horizon", "do not apply"),
    ({"backend": "jax"}, "backend", None),  # a server without JAX, or: numpy only
])
def test_horizon_refusals_are_422_naming_the_field(client, rec, extra, field, needle):
    u, y = rec
    body = {"u": u.tolist(), "y": y.tolist(), "fs": FS, "method": "linear", "horizon": 8, **extra}
    r = client.post(URL, json=body)
    if field == "backend" and r.json().get("field") == "horizon":
        field = "horizon"  # JAX is installed here: the k-step prediction itself is numpy only
    p = _problem(r, 422, field)
    if needle:
        assert needle in p["detail"]


def test_loops_and_novelty_refuse_a_horizon(client, rec):
    u, y = rec
    body = {"u": u.tolist(), "y": y.tolist(), "fs": FS, "method": "linear", "horizon": 8}
    p = _problem(client.post("/v1/models/boucwen/loops", json=body), 422, "horizon")
    assert "predict" in p["detail"]


def test_a_record_with_a_gap(client, model, rec):
    u, y = rec
    a, b = 150, 170
    uj = [None if a <= i < b else float(v) for i, v in enumerate(u)]
    body = {"u": uj, "y": y.tolist(), "fs": FS, "method": "linear"}
    r = client.post(URL, json=body)
    assert r.status_code == 200, r.text[:400]
    ans = r.json()
    assert ans["gaps"] == [{"start": a, "end": b, "start_s": a / FS, "end_s": b / FS}]
    assert all(v is None for v in ans["mean"][a:b]) and all(v is None for v in ans["std"][a:b])
    assert all(v is not None for v in ans["mean"][:a] + ans["mean"][b:])
    ug = u.copy()
    ug[a:b] = np.nan
    run = model.simulate(ug, y=y, method="linear")
    np.testing.assert_allclose(np.array(ans["mean"], dtype=float), run.mean, rtol=1e-12, atol=0)
    keep = ~np.isnan(run.mean)
    assert ans["fit"] == pytest.approx(fit_percent(y[keep], run.mean[keep]), rel=1e-12)
    # a gap in y alone, and with a horizon
    yj = [None if a <= i < b else float(v) for i, v in enumerate(y)]
    both = client.post(URL, json={"u": u.tolist(), "y": yj, "fs": FS, "method": "linear", "horizon": 8}).json()
    assert both["horizon"] == 8 and both["gaps"][0]["start"] == a and both["mean"][a] is None
    # an NPZ body's NaN is a gap too
    buf = io.BytesIO()
    np.savez(buf, u=ug, y=y, fs=FS)
    npz = client.post(URL + "?method=linear", content=buf.getvalue(), headers={"content-type": "application/x-npz"})
    assert npz.status_code == 200 and npz.json()["gaps"] == ans["gaps"]
    # a record without a gap answers as before: no gaps member
    assert "gaps" not in client.post(URL, json={**body, "u": u.tolist()}).json()


def test_gap_refusals_name_the_field(client, rec):
    u, y = rec
    long_u = np.tile(u, 5)
    n = long_u.size  # 2000 samples at 750 Hz
    gap = [None if 100 <= i < 100 + int(2 * FS) + 1 else float(v) for i, v in enumerate(long_u)]
    p = _problem(client.post(URL, json={"u": gap, "fs": FS, "method": "linear"}), 422, "u")
    assert "the limit is 2 s" in p["detail"] and p["limit"] == 2.0
    mostly = [None if i % 100 < 60 else float(v) for i, v in enumerate(long_u)]
    p = _problem(client.post(URL, json={"u": mostly, "fs": FS, "method": "linear"}), 422, "u")
    assert f"{int(0.6 * n)} of {n} samples are missing" in p["detail"]
    yg = [None if 10 <= i < 20 else float(v) for i, v in enumerate(y)]
    _problem(client.post("/v1/models/boucwen/loops", json={"u": u.tolist(), "y": yg, "fs": FS}), 422, "y")
    _problem(client.post("/v1/models/boucwen/novelty", json={"u": u.tolist(), "y": yg, "fs": FS}), 422, "y.10")
    _problem(client.post(URL, json={"u": u.tolist(), "y": yg, "fs": FS, "return_state": True}), 422, "y")
    _problem(client.post(URL, json={"u": [None] * 50, "fs": FS}), 422, "u")
    p = _problem(client.post(URL, content=b'{"u": [NaN, 1.0], "fs": 750}',
                             headers={"content-type": "application/json"}), 422, "u.0")
    assert "finite" in p["detail"]  # the NaN token stays refused: a gap is null


def test_cli_predict_horizon_and_gaps(registry, model, rec, tmp_path, capsys):
    u, y = rec
    path = tmp_path / "rec.npz"
    np.savez(path, u=u, y=y, fs=FS)
    base = ["predict", "--registry", str(registry), "--model", "boucwen", "--method", "linear", "--json"]
    assert main([*base, str(path), "--horizon", "16"]) == 0
    a = json.loads(capsys.readouterr().out)
    run = model.simulate(u, y=y, horizon=16, method="linear")
    assert a["horizon"] == 16 and a["fit"] == pytest.approx(fit_percent(y, run.mean), rel=1e-12)
    assert main([*base, str(path), "--horizon", "16", "--start", "measured"]) == 1
    assert "horizon" in capsys.readouterr().err
    ug = u.copy()
    ug[50:60] = np.nan
    gpath = tmp_path / "gap.csv"
    np.savetxt(gpath, np.column_stack([np.arange(u.size) / FS, ug, y]), delimiter=",", header="time,u,y",
               comments="")
    assert main([*base, str(gpath), "--out", str(tmp_path / "out.npz")]) == 0
    g = json.loads(capsys.readouterr().out)
    assert g["gaps"][0]["start"] == 50 and g["gaps"][0]["end"] == 60 and g["mean"][55] is None
    assert np.isnan(np.load(tmp_path / "out.npz")["mean"][50:60]).all()
    # a gap past the limit: exit code 1, one line naming the field and the limit
    long_u = np.tile(u, 5)
    long_u[10:10 + int(2 * FS) + 1] = np.nan
    lpath = tmp_path / "long-gap.npz"
    np.savez(lpath, u=long_u, y=np.tile(y, 5), fs=FS)
    assert main([*base, str(lpath)]) == 1
    err = capsys.readouterr().err
    assert "u has a gap of 1501 samples" in err and "the limit is 2 s" in err and len(err.strip().splitlines()) == 1
    # loops reads the same file and refuses it, as before
    assert main(["loops", "--registry", str(registry), "--model", "boucwen", str(gpath)]) == 1
    assert "NaN" in capsys.readouterr().err
