"""A new user's first CLI calls (issue: a new user's first hour): an unknown model's error lists the
registry's models, a bad record fails before the default registry is built, and --mc defaults to the
bundle's config."""
from __future__ import annotations

import json

import numpy as np
import pytest
from test_service_support import FS, built_registry, copy_registry

from gpnarx.cli.main import main
from gpnarx.storage.bundle import save_bundle


@pytest.fixture(scope="module")
def registry(tmp_path_factory):
    return copy_registry(tmp_path_factory.mktemp("cli-first") / "registry")


@pytest.fixture
def record(tmp_path):
    b = built_registry()
    path = tmp_path / "rec.npz"
    np.savez(path, u=b.test_u[:300], y=b.test_y[:300], fs=FS)
    return path


def test_unknown_model_lists_the_registry_models(registry, record, capsys):
    assert main(["predict", "--registry", str(registry), "--model", "nope", str(record)]) == 1
    err = capsys.readouterr().err
    assert "model 'nope' not found" in err and "available: boucwen, plain" in err, err


def test_unknown_model_in_an_empty_registry_says_none_and_what_to_do(tmp_path, record, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["predict", "--registry", str(tmp_path / "empty"), "--model", "bouc-wen", str(record)]) == 1
    err = capsys.readouterr().err
    assert "available: none" in err and "build-defaults" in err, err


def test_a_bad_record_fails_before_the_default_registry_is_built(tmp_path, monkeypatch, capsys):
    from gpnarx.training import defaults

    monkeypatch.delenv("GPNARX_REGISTRY", raising=False)
    built = []
    monkeypatch.setattr(defaults, "ensure_default_registry", lambda *a, **k: built.append(1) or str(tmp_path))
    bad = tmp_path / "bad.csv"
    bad.write_text("time,force\n0,1\n0.001,2\n0.002,3\n")
    assert main(["predict", "--model", "bouc-wen", str(bad)]) == 1
    err = capsys.readouterr().err
    assert "bad.csv" in err and "'u'" in err, err
    assert built == [], "the default registry was built before the record was checked"
    assert main(["predict", "--model", "bouc-wen", "--mc", "0", str(bad)]) == 2  # options too
    assert built == []


def test_mc_defaults_to_the_bundle_config(registry, record, capsys):
    b = built_registry()
    save_bundle(b.model, registry, "light", "1", fs=FS, units={"u": "N", "y": "m"}, physics=None, novelty=None,
                training={}, extra={"predict": {"method": "mc", "mc_paths": 16}})
    assert main(["--json", "predict", "--registry", str(registry), "--model", "light", str(record)]) == 0
    assert json.loads(capsys.readouterr().out)["mc_paths"] == 16
    assert main(["--json", "predict", "--registry", str(registry), "--model", "light", "--mc", "8", str(record)]) == 0
    assert json.loads(capsys.readouterr().out)["mc_paths"] == 8


def test_train_without_json_prints_a_readable_summary(tmp_path, monkeypatch, capsys):
    """`gpnarx train` without --json: the bundle, the run's figures with units and a table by record, not a
    Python dict repr; with --json the answer is unchanged."""
    import gpnarx.training.pipeline as pipeline

    bundle = tmp_path / "reg" / "toy" / "1"
    bundle.mkdir(parents=True)
    (bundle / "manifest.json").write_text(json.dumps({"units": {"u": "N", "y": "m"}}))
    metrics = {"fit_seconds": 8.27, "n_train": 1000, "n_rows": 4064, "nlml": -678.5, "mc_paths": 128,
               "method": "mc", "train_records": ["sweep-10N"],
               "records": {"sweep-50N": {"role": "verify", "use": "lag-selection", "fit": 89.536,
                                         "rmse": 4.44e-05, "coverage": 99.9, "band_width": 2.98e-4,
                                         "n_samples": 2052, "psd_peaks_measured": [41.0, 26.4]}}}
    monkeypatch.setattr(pipeline, "train", lambda *a, **k: {"name": "toy", "version": "1", "path": str(bundle),
                                                            "metrics": metrics})
    assert main(["train", "bouc-wen", "--registry", str(tmp_path / "reg"), "--no-report"]) == 0
    out = capsys.readouterr().out
    assert "{" not in out and "'" not in out, out  # no dict repr
    assert f"bundle toy version 1 written to {bundle}" in out
    assert "fit 8.27 s" in out and "1000 training points of 4064 rows" in out
    header = next(line for line in out.splitlines() if line.startswith("record"))
    assert "fit [%]" in header and "RMSE [m]" in header and "coverage [%]" in header
    row = next(line for line in out.splitlines() if line.startswith("sweep-50N"))
    assert "89.54" in row and "4.440e-05" in row and "2052" in row
    assert main(["--json", "train", "bouc-wen", "--registry", str(tmp_path / "reg"), "--no-report"]) == 0
    assert json.loads(capsys.readouterr().out)["metrics"] == metrics


def test_default_registry_means_what_serve_means(tmp_path, monkeypatch, record, capsys):
    """Without --registry the CLI uses the folder serve uses ($GPNARX_REGISTRY, even empty, else the cache)
    and builds the default asked for there (only that one, and its source), none for another model."""
    from gpnarx.training import defaults

    reg = tmp_path / "empty-registry"
    monkeypatch.setenv("GPNARX_REGISTRY", str(reg))
    calls = []

    def fake(path=None, progress=True, names=None, **kw):
        calls.append(list(names) if names is not None else None)
        root = defaults.default_registry_dir()
        root.mkdir(parents=True, exist_ok=True)
        return root

    monkeypatch.setattr(defaults, "ensure_default_registry", fake)
    assert main(["predict", "--model", "bouc-wen", str(record)]) == 1  # the fake built nothing
    assert calls == [["bouc-wen"]] and reg.is_dir()
    assert f"not found in registry {reg}" in capsys.readouterr().err
    assert main(["novelty", "--model", "bert-real-monitor", str(record)]) == 1
    assert calls[-1] == ["bert-real", "bert-real-monitor"]
    calls.clear()
    assert main(["predict", "--model", "my-structure", str(record)]) == 1
    assert calls == [] and "available: none" in capsys.readouterr().err
