"""The wheel a user installs: one import package ``gpnarx`` with its shipped configs, usable from any folder.

Builds a wheel from a clean copy of the sources (a stale ``build/`` folder in the checkout could
otherwise leak deleted modules into it), checks its file list, installs it into a fresh venv and
runs the console script and an import of every layer from an empty folder. The venv sees the
packages of the environment the tests run in (tests/venv_support.py: the user's venv or the
machine's interpreter) so no dependency is downloaded; the check that ``gpnarx`` resolves inside
the venv guards against the editable install of the checkout answering instead of the wheel.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from importlib import metadata
from pathlib import Path

import pytest
from venv_support import make_venv

ROOT = Path(__file__).resolve().parents[1]
GENERIC_TOP_LEVEL = {"model", "operations", "service", "training", "configs", "cli", "tests", "bench", "studies",
                     "tools"}
# the repository's studies (studies/*.py): run from a checkout by gpnarx reproduce, never shipped
STUDY_MODULES = {p.stem for p in (ROOT / "studies").glob("*.py") if p.stem != "__init__"}
SHIPPED = {"bouc-wen", "bert-standin", "bert-standin-monitor", "bert-real"}
_IGNORE_NAMES = shutil.ignore_patterns(".git", "build", "dist", "*.egg-info", "__pycache__", "*.pyc", ".hypothesis",
                                       ".pytest_cache", ".benchmarks", ".lagcache", "runs", "registry", "reports",
                                       ".venv", ".ci-venv", "tests", "bench")


def _COPY_IGNORE(folder, names):
    """The names above, and any virtual environment (a folder with pyvenv.cfg) whatever the user called it."""
    return set(_IGNORE_NAMES(folder, names)) | {n for n in names if (Path(folder) / n / "pyvenv.cfg").is_file()}


def _clean_env() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP")}
    env.update(PYTHONNOUSERSITE="1", PIP_DISABLE_PIP_VERSION_CHECK="1", PIP_NO_INPUT="1")
    return env


def _setuptools_is_new_enough() -> bool:
    """True when this interpreter can build the wheel itself (pyproject asks setuptools>=68 and wheel):
    then the build needs no network (no isolated build environment to fill)."""
    try:
        major = int(metadata.version("setuptools").split(".")[0])
        metadata.version("wheel")
    except (metadata.PackageNotFoundError, ValueError):
        return False
    return major >= 68


def _run(cmd, cwd, timeout=120):
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, env=_clean_env(), capture_output=True, text=True,
                          timeout=timeout)
    assert proc.returncode == 0, f"{cmd} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    src = tmp_path_factory.mktemp("src") / "gpnarx-src"
    shutil.copytree(ROOT, src, ignore=_COPY_IGNORE)
    out = tmp_path_factory.mktemp("wheelhouse")
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", out, src]
    if _setuptools_is_new_enough():
        cmd.insert(4, "--no-build-isolation")
    _run(cmd, cwd=out, timeout=180)
    wheels = list(out.glob("gpnarx-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


def test_wheel_holds_one_import_package_and_the_shipped_configs(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names}
    dist_info = {t for t in top if t.endswith(".dist-info")}
    assert top - dist_info == {"gpnarx"}, f"unexpected top-level entries: {sorted(top - dist_info)}"
    assert not (top & GENERIC_TOP_LEVEL)
    for sub in ("model", "training", "training/pages", "training/simulators", "service", "cli", "configs"):
        assert f"gpnarx/{sub}/__init__.py" in names, sub
    configs = {Path(n).stem for n in names if n.startswith("gpnarx/configs/") and n.endswith(".toml")}
    assert SHIPPED <= configs, configs
    entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    assert "gpnarx = gpnarx.cli.main:main" in zipfile.ZipFile(wheel).read(entry_points).decode()
    assert {"cycle_study", "real_table", "frf_check", "exact_study"} <= STUDY_MODULES
    shipped_modules = {Path(n).stem for n in names if n.endswith(".py")}
    assert not shipped_modules & STUDY_MODULES, f"study modules in the wheel: {sorted(shipped_modules & STUDY_MODULES)}"


_SNIPPET = """
import json, sys
import gpnarx, gpnarx.model, gpnarx.service.app
from gpnarx.training.config import load_config
from gpnarx.training.defaults import shipped_config, shipped_config_names
cfg = load_config(shipped_config("bouc-wen"))
print(json.dumps({"prefix": sys.prefix, "gpnarx": gpnarx.__file__, "model": gpnarx.model.__file__,
                  "config": str(cfg.path), "name": cfg.name, "shipped": shipped_config_names()}))
"""


def test_wheel_installs_into_a_fresh_venv_and_runs_from_an_empty_folder(wheel, tmp_path):
    env_dir = tmp_path / "venv"
    # no pip inside the venv (ensurepip is the slow part); the running pip installs into it
    py = make_venv(env_dir, with_pip=False)
    bindir = py.parent
    _run([sys.executable, "-m", "pip", "--python", py, "install", "--no-deps", "--no-index", "-q", wheel],
         cwd=tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()

    site = Path(_run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], cwd=empty)
                .stdout.strip())
    for name in GENERIC_TOP_LEVEL:
        assert not (site / name).exists(), f"site-packages holds a top-level {name!r}"

    out = json.loads(_run([py, "-c", _SNIPPET], cwd=empty).stdout.strip().splitlines()[-1])
    venv_root = env_dir.resolve()
    for key in ("gpnarx", "model", "config"):
        assert Path(out[key]).resolve().is_relative_to(venv_root), f"{key} resolved outside the venv: {out[key]}"
    assert out["name"] == "bouc-wen" and SHIPPED <= set(out["shipped"])

    helptext = _run([bindir / "gpnarx", "--help"], cwd=empty).stdout
    for cmd in ("simulate", "train", "predict", "serve"):
        assert cmd in helptext
    # a study is the checkout's: the installed package says so, in one line, with exit code 1
    study = subprocess.run([str(bindir / "gpnarx"), "reproduce", "cycle-study", "--", "--help"], cwd=empty,
                           env=_clean_env(), capture_output=True, text=True, timeout=120)
    assert study.returncode == 1 and "checkout" in study.stderr and "Traceback" not in study.stderr, study.stderr
    assert list(empty.iterdir()) == [], "running from an empty folder wrote files into it"


def test_train_takes_a_shipped_config_by_name_from_any_folder(tmp_path, monkeypatch):
    from gpnarx.cli.cmd_train import resolve_config
    from gpnarx.cli.errors import CLIError
    from gpnarx.training.defaults import shipped_config

    monkeypatch.chdir(tmp_path)
    assert resolve_config("bouc-wen") == shipped_config("bouc-wen")
    (tmp_path / "bouc-wen").write_text("")  # an existing file of that name wins
    assert resolve_config("bouc-wen") == Path("bouc-wen")
    assert resolve_config("my.toml") == Path("my.toml")  # a path is left to the config reader
    with pytest.raises(CLIError, match="shipped: .*bouc-wen"):
        resolve_config("no-such-config")


def test_wheel_ships_storage_apart_from_the_method(wheel):
    """gpnarx.storage holds the files and objects (bundles, registry, fsspec, atomic writes, record files);
    gpnarx.model ships the method only, and gpnarx.runtime (process tuning) sits at the package root."""
    names = set(zipfile.ZipFile(wheel).namelist())
    assert "storage" not in {n.split("/")[0] for n in names}
    for mod in ("__init__", "bundle", "registry", "remote", "atomicio", "record_formats", "record_formats_lab",
                "record_files", "jsonsafe"):
        assert f"gpnarx/storage/{mod}.py" in names, mod
    assert "gpnarx/runtime.py" in names and "gpnarx/model/record.py" in names
    in_model = {Path(n).stem for n in names if n.startswith("gpnarx/model/") and n.endswith(".py")}
    storage_modules = {"bundle", "registry", "storage", "remote", "atomicio", "record_formats", "record_formats_lab",
                       "records", "record_files", "jsonsafe", "runtime"}
    assert not in_model & storage_modules, sorted(in_model & storage_modules)
    # the front ends' operations ship as gpnarx.operations, apart from the method too
    for mod in ("__init__", "base", "run", "predict", "loops", "novelty", "stream_token", "cycle_stream",
                "novelty_window"):
        assert f"gpnarx/operations/{mod}.py" in names, mod
    front_end_modules = {"operations", "stream_token", "cycle_stream", "novelty_window", "archive_bounds"}
    assert not in_model & front_end_modules, sorted(in_model & front_end_modules)
