"""One default per setting (issue 32 item 9): Monte Carlo paths come from the bundle's config in the CLI, the HTTP
service and the /ui page alike (``operations.default_mc_paths``), and a record file without a sampling
frequency is refused by the CLI unless ``--fs`` is given, as ``POST /v1/records/parse`` refuses it without ``fs``."""
import json
import re

import numpy as np
import pytest
from fastapi.testclient import TestClient
from test_service_support import FS, MC_PATHS, copy_registry, short_record

from gpnarx.cli.main import main
from gpnarx.operations import DEFAULT_MC_PATHS, default_mc_paths
from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings

STATIC = __import__("gpnarx.service", fromlist=["x"]).__path__[0] + "/static/ui"


def test_default_mc_paths_rule():
    assert default_mc_paths({"predict": {"mc_paths": 300}}) == 300
    assert default_mc_paths({"predict": {"mc_paths": 300}}, "loops") == 300
    # novelty: the paths its threshold was calibrated with; a linearised calibration (0) falls back
    assert default_mc_paths({"predict": {"mc_paths": 300}, "novelty": {"mc_paths": 128}}, "novelty") == 128
    assert default_mc_paths({"predict": {"mc_paths": 300}, "novelty": {"mc_paths": 0}}, "novelty") == 300
    assert default_mc_paths({}) == DEFAULT_MC_PATHS == 1024  # training.config_schema's [predict] mc_paths
    assert default_mc_paths({"predict": {"mc_paths": "bad"}}) == DEFAULT_MC_PATHS


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("mc")
    reg = copy_registry(tmp / "reg")
    u, y = short_record(n=64, seed=3)
    rec = tmp / "r.npz"
    np.savez(rec, u=u, y=y, fs=FS)
    return reg, rec, u, y


def test_cli_http_and_page_use_the_bundle_config_paths(setup, capsys):
    reg, rec, u, y = setup
    assert MC_PATHS != DEFAULT_MC_PATHS and MC_PATHS != 256  # the bundle's config, not a fallback
    cli = {}
    for op in ("predict", "loops", "novelty"):
        assert main(["--json", op, "--registry", str(reg), "--model", "boucwen:2", str(rec)]) == 0
        cli[op] = json.loads(capsys.readouterr().out)
    assert cli["predict"]["mc_paths"] == cli["loops"]["mc_paths"] == MC_PATHS

    client = TestClient(create_app(reg, Settings.from_env({}, registry_poll=0.0, workers=1)))
    detail = client.get("/v1/models/boucwen/versions/2").json()
    assert detail["default_mc_paths"] == {op: default_mc_paths({"predict": {"mc_paths": MC_PATHS}}, op)
                                          for op in ("predict", "loops", "novelty")}
    body = {"u": u.tolist(), "y": y.tolist(), "fs": FS, "seed": 0}  # the page's request: no mc_paths
    for op in ("predict", "loops", "novelty"):
        r = client.post(f"/v1/models/boucwen/versions/2/{op}", json=body)
        assert r.status_code == 200, r.text
        if op != "novelty":
            assert r.json()["mc_paths"] == cli[op]["mc_paths"] == detail["default_mc_paths"][op]
    r = client.post("/v1/batch", json={"requests": [{"model": "boucwen", "version": "2", "operation": "predict",
                                                      **body}]})
    assert r.status_code == 200, r.text
    assert r.json()["results"][0]["mc_paths"] == MC_PATHS

    # an operator's GPNARX_MC_PATHS_DEFAULT still overrides the model's, and says so in the detail
    client = TestClient(create_app(reg, Settings.from_env({"GPNARX_MC_PATHS_DEFAULT": "16"}, registry_poll=0.0,
                                                          workers=1)))
    assert client.get("/v1/models/boucwen/versions/2").json()["default_mc_paths"]["predict"] == 16
    assert client.post("/v1/models/boucwen/versions/2/predict", json=body).json()["mc_paths"] == 16


def test_page_paths_default_is_in_sight_and_novelty_runs_as_calibrated():
    """The /ui page's paths field holds its interactive default, 64, where the user sees it (the model's default,
    up to 4096 paths, made a run take a minute), and says what it costs next to it; emptied, the model's default
    applies. Novelty is sent no paths or method: it runs as its threshold was calibrated. The requests the page
    sends are checked in tests/test_ui_browser.py."""
    js = open(f"{STATIC}/app.js").read()
    html = open(f"{STATIC}/index.html").read()
    field = re.search(r'<input id="mc-paths"[^>]*>', html).group(0)
    assert 'value="64"' in field
    assert 'id="paths-note"' in html
    assert not re.search(r"mc_paths:\s*Math", js), "the paths are those of the field, not a default in the code"
    assert "default_mc_paths" in js  # the model's, from GET /v1/models/NAME, in the note


def test_csv_without_time_needs_fs(setup, tmp_path, capsys):
    reg, _, u, y = setup
    csv = tmp_path / "no_time.csv"
    np.savetxt(csv, np.column_stack([u, y]), delimiter=",", header="u,y", comments="")
    rc = main(["predict", "--registry", str(reg), "--model", "boucwen:2", str(csv)])
    err = capsys.readouterr().err
    assert rc == 2 and "--fs" in err and "no sampling frequency" in err, err
    assert main(["--json", "predict", "--registry", str(reg), "--model", "boucwen:2", str(csv),
                 "--fs", str(FS), "--mc", "8"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["n"] == len(u) and out["mc_paths"] == 8
    # a wrong --fs is the model's fs mismatch, a runtime error naming both
    rc = main(["predict", "--registry", str(reg), "--model", "boucwen:2", str(csv), "--fs", "100"])
    assert rc == 1 and "fs" in capsys.readouterr().err
    # the HTTP parse route refuses it likewise without its fs field, and takes it with one
    client = TestClient(create_app(reg, Settings.from_env({}, registry_poll=0.0, workers=1)))
    r = client.post("/v1/records/parse", files=[("files", ("no_time.csv", csv.read_bytes()))])
    assert r.status_code == 422 and r.json()["field"] == "fs", r.text
    r = client.post("/v1/records/parse", files=[("files", ("no_time.csv", csv.read_bytes()))], data={"fs": str(FS)})
    assert r.status_code == 200 and r.json()["fs"] == FS, r.text


def test_every_record_command_declares_the_same_fs_option(monkeypatch):
    """--fs is declared once (cli.cmd_predict.add_fs_argument) for every command that reads record files: the
    same help text everywhere, and the same refusal of a non-positive value."""
    import argparse

    from gpnarx.cli import cmd_predict
    from gpnarx.cli.main import build_parser

    calls = []
    real = cmd_predict.add_fs_argument
    for mod in ("cmd_predict", "cmd_calibrate", "cmd_predict_many", "cmd_stream"):
        monkeypatch.setattr(f"gpnarx.cli.{mod}.add_fs_argument", lambda p, real=real: (calls.append(p.prog), real(p)))
    parser = build_parser()
    commands = {"predict", "loops", "novelty", "calibrate", "predict-many", "stream", "validate"}
    assert {c.split()[-1] for c in calls} == commands, calls
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    helps = {next(a.help for a in subs[c]._actions if "--fs" in a.option_strings) for c in commands}
    assert len(helps) == 1 and "sampling frequency [Hz]" in helps.pop()
    with pytest.raises(Exception, match="--fs must be a finite positive"):
        cmd_predict.read_cli_record("any.csv", fs=-1.0)
