"""A new user's first hour with the CLI and the service (issue 50): a record written by ``gpnarx simulate`` is a
request body as it is, ``predict`` prints what the README says in readable numbers, a misspelt option is named as
such, and the Monte Carlo path limit is one number for the CLI and the service."""
from __future__ import annotations

import contextlib
import io
import re

import numpy as np
import pytest
from fastapi.testclient import TestClient
from test_service_support import FS, built_registry, short_record

from gpnarx.cli.main import main
from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings

NPZ = {"content-type": "application/x-npz"}


def cli(*argv) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def client():
    return TestClient(create_app(built_registry().root, Settings(workers=1, queue_size=4)),
                      raise_server_exceptions=False)


def npz(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


# ------------------------------------------------------------------------ NPZ bodies: our own record files
def test_an_npz_written_by_gpnarx_simulate_is_a_request_body(client, tmp_path):
    out = tmp_path / "sine.npz"
    code, _, err = cli("simulate", "bouc-wen", "--excitation", "sine", "--freq", "35.59", "--amplitude", "10",
                       "--duration", "0.2", "--seed", 4, "--out", out)
    assert code == 0, err
    with np.load(out) as d:
        assert {"units_u", "units_y", "name"} <= set(d.files)  # what the record files hold besides u, y, fs
        n = d["u"].size
    r = client.post("/v1/models/boucwen/predict?mc_paths=8&seed=0", content=out.read_bytes(), headers=NPZ)
    assert r.status_code == 200, r.text
    assert len(r.json()["mean"]) == n and r.json()["fit"] is not None


def test_npz_units_are_checked_against_the_models(client):
    u, y = short_record(64)
    base = {"u": u, "y": y, "fs": np.float64(FS), "name": np.str_("run 1")}
    ok = client.post("/v1/models/boucwen/predict?mc_paths=8", headers=NPZ,
                     content=npz(**base, units_u=np.str_("N"), units_y=np.str_("")))  # empty: not stated
    assert ok.status_code == 200, ok.text
    for key, label in (("units_u", "V"), ("units_y", "mm")):
        r = client.post("/v1/models/boucwen/predict?mc_paths=8", headers=NPZ,
                        content=npz(**base, **{key: np.str_(label)}))
        assert r.status_code == 422, r.text
        p = r.json()
        assert p["field"] == key and repr(label) in p["detail"] and "boucwen" in p["detail"], p
    r = client.post("/v1/models/boucwen/predict?mc_paths=8", headers=NPZ,
                    content=npz(**base, units_u=np.str_("furlong")))
    assert r.status_code == 422 and r.json()["field"] == "units_u", r.text
    r = client.post("/v1/models/boucwen/predict?mc_paths=8", headers=NPZ, content=npz(**base, units_u=np.float64(1.0)))
    assert r.status_code == 422 and r.json()["field"] == "units_u", r.text
    r = client.post("/v1/models/boucwen/predict?mc_paths=8", headers=NPZ, content=npz(**base, notes=np.str_("x")))
    assert r.status_code == 422 and r.json()["field"] == "notes", r.text  # anything else is still refused


# ------------------------------------------------------------------------ predict's printed answer
def test_predict_prints_readable_numbers_and_the_arrays_it_names(tmp_path):
    u, y = short_record(120)
    rec = tmp_path / "r.npz"
    np.savez(rec, u=u, y=y, fs=FS)
    code, out, err = cli("predict", "--registry", built_registry().root, "--model", "plain", rec, "--mc", 8)
    assert code == 0, err
    lines = dict(line.split(": ", 1) for line in out.strip().splitlines())
    for key in ("mean", "lower", "upper", "std"):  # the README: predict prints them
        assert re.fullmatch(r"120 values from \S+ to \S+ \(--json for all\)", lines[key]), lines[key]
    for key in ("fit", "rmse", "coverage", "seconds"):
        digits = re.sub(r"e[+-]\d+$", "", lines[key]).replace("-", "").replace(".", "").lstrip("0")
        assert len(digits) <= 6, (key, lines[key])  # never 96.39999999999999


# ------------------------------------------------------------------------ a misspelt option
def test_a_misspelt_option_is_named_not_reported_as_a_missing_one(tmp_path):
    rec = tmp_path / "r.npz"
    np.savez(rec, u=np.zeros(32), fs=FS)
    code, _, err = cli("predict", "--modle", "bouc-wen", rec)
    assert code == 2
    assert "unrecognized argument" in err and "--modle" in err and "--model" in err, err
    assert "required" not in err, err
    code, _, err = cli("predict", "--model", "bouc-wen", rec, "--sed", "3")
    assert code == 2 and "--sed" in err and "did you mean --seed" in err, err


# ------------------------------------------------------------------------ one Monte Carlo path limit
def test_one_monte_carlo_path_limit_for_the_cli_and_the_service(client, monkeypatch):
    from gpnarx.cli.cmd_predict import mc_paths
    from gpnarx.cli.errors import UsageError
    from gpnarx.operations import MC_PATHS_MAX

    assert Settings().mc_paths_max == MC_PATHS_MAX
    assert mc_paths(MC_PATHS_MAX) == MC_PATHS_MAX
    with pytest.raises(UsageError, match=f"--mc: mc_paths {MC_PATHS_MAX + 1} exceeds the limit of {MC_PATHS_MAX} "):
        mc_paths(MC_PATHS_MAX + 1)
    with pytest.raises(UsageError, match="--mc: mc_paths must be at least 1, got 0"):
        mc_paths(0)
    u, _ = short_record(32)
    r = client.post("/v1/models/boucwen/predict", json={"u": u.tolist(), "fs": FS, "mc_paths": MC_PATHS_MAX + 1})
    assert r.status_code == 422 and r.json()["limit"] == MC_PATHS_MAX
    monkeypatch.setenv("GPNARX_MC_PATHS_MAX", str(2 * MC_PATHS_MAX))  # an operator's raised bound holds for both
    assert Settings.from_env().mc_paths_max == mc_paths(2 * MC_PATHS_MAX) == 2 * MC_PATHS_MAX
