"""Training on the core install (no extra ``train``: neither matplotlib nor tqdm): ``gpnarx lags`` says how far
it is, cell by cell, and that it skips its heat map and why; a training report (the default bundles' on first
use) is written without figures, saying why and how to get them."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

from test_pipeline import SMALL_CONFIG

from gpnarx.configs import shipped_config
from gpnarx.training import report as rp

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = textwrap.dedent('''
    import io, json, sys, warnings
    from contextlib import redirect_stderr, redirect_stdout
    for name in ("matplotlib", "tqdm"):
        sys.modules[name] = None  # every import of them fails, as in a core install
    from gpnarx.cli.main import main
    from gpnarx.training.pipeline import train

    cfg, tmp = sys.argv[1], sys.argv[2]
    err, out = io.StringIO(), io.StringIO()
    with redirect_stderr(err), redirect_stdout(out):
        code = main(["lags", cfg, "--ny", "2:4:2", "--nu", "2:2", "--jobs", "1", "--out", tmp + "/surface.json",
                     "--cache-dir", tmp + "/cache"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = train(cfg, tmp + "/reg", mc_paths=8, report=True, report_method="linear")
    print(json.dumps({"code": code, "stderr": err.getvalue(), "stdout": out.getvalue(), "bundle": res["path"]}))
''')


def test_lags_and_train_on_the_core_install(tmp_path):
    cfg = tmp_path / "small.toml"
    cfg.write_text(SMALL_CONFIG.format(ny=2, nu=2))
    proc = subprocess.run([sys.executable, "-c", SCRIPT, str(cfg), str(tmp_path)], cwd=ROOT, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["code"] == 0, out["stderr"]
    err = out["stderr"]
    # progress: a line when it starts and one per finished cell, on stderr
    assert "lag surface: 0/2 cells (0 %), started" in err, err
    assert "lag surface: 1/2 cells (50 %)" in err and "lag surface: 2/2 cells (100 %)" in err, err
    # the heat map: said to be skipped, why and how to get it
    note = next(line for line in err.splitlines() if "surface.png" in line)
    assert "not written" in note and "matplotlib is not installed" in note and "gpnarx[train]" in note, note
    assert (tmp_path / "surface.json").is_file() and not (tmp_path / "surface.png").exists()
    assert "figure_skipped: surface.png not written" in out["stdout"]
    # the training report: written, without figures, saying why and how to get them
    report = Path(out["bundle"]) / "report"
    data = json.loads((report / "report.json").read_text())
    assert "gpnarx[train]" in data["figures_missing"] and data["records"], data["figures_missing"]
    page = (report / "report.html").read_text()
    assert "No figures: matplotlib is not installed" in page and "<img" not in page
    assert "Per-record metrics" in page and not list(report.glob("*.png"))


def test_report_without_figures_names_the_command_that_trains_again(tmp_path, monkeypatch):
    from test_report import _sine_record

    monkeypatch.setattr(rp, "record_figure", None)
    monkeypatch.setattr(rp, "lag_surface_figure", None)
    rows = [{"ny": 2, "nu": 2, "fit": 80.0}, {"ny": 4, "nu": 2, "fit": 85.0}]
    paths = rp.write_report(tmp_path / "r", "r", {"config": str(shipped_config("bouc-wen"))}, [_sine_record()],
                            lag_surface={"cells": rows, "chosen": {"ny": 4, "nu": 2}})
    missing = json.loads(paths["json"].read_text())["figures_missing"]
    assert "pip install 'gpnarx[train]'" in missing and "gpnarx train bouc-wen --registry REGISTRY" in missing
    assert paths["records"] == {} and paths["lag_surface"] is None and not list((tmp_path / "r").glob("*.png"))
    own = tmp_path / "mine.toml"
    missing = rp.figures_missing({"config": str(own)})
    assert f"gpnarx train {own} --registry REGISTRY" in missing
