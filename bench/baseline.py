"""Frozen baselines from git history: earlier product code, taken from a commit, not copied into the tree.

``load_model(ref)`` exports the ``model/`` folder of a git ref (``git archive``) once into a cache keyed by
the ref's commit (``$XDG_CACHE_HOME/gpnarx/bench-baseline/COMMIT/``) and imports it into the bench process as
a package of its own, ``_baseline_<commit12>``, beside the installed product. Its code is the product's as it
stood at that commit, kernels and posteriors included. ``model/`` imports itself by relative imports only, so
the product's modules do not leak into it; a ref whose ``model/`` names ``gpnarx`` is refused.
``fitted_copy`` gives the baseline the product's fitted model through the bundle contract
(``fitted_description`` and ``fitted_arrays``), so both sides run the same posterior.

A clone without the commit (a shallow clone) cannot build a baseline: ``BaselineUnavailable`` says why, with a
short ``code`` for the bench's RESULT line (``baseline_skipped=CODE``), and the bench skips its baseline.
"""
from __future__ import annotations

import importlib
import importlib.util
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# bench_mc_speed.py: the parent of 3441adf, the commit that fused the Monte Carlo local model (gp.LocalModel):
# simulate_mc with one gp.local_model call per step and McPaths shifting the (P x ny) lags every step
MC_BASELINE = "9ee9349f2ececaf5e95a6779b9af7e2e9ba2d91a"


class BaselineUnavailable(RuntimeError):
    """The baseline cannot be built here; ``code`` is a one-word reason for a RESULT line."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


def _git(repo: Path, *args: str) -> subprocess.CompletedProcess:
    try:
        return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, check=False)
    except FileNotFoundError:
        raise BaselineUnavailable("no-git", "git is not installed: the baseline comes from the git history") from None


def resolve(ref: str, repo: Path = ROOT) -> str:
    """The commit ``ref`` names in ``repo``; ``BaselineUnavailable`` when it is not there."""
    if _git(repo, "rev-parse", "--git-dir").returncode != 0:
        raise BaselineUnavailable("not-a-checkout", f"{repo} is not a git checkout: the baseline {ref} comes from "
                                                    "the git history")
    found = _git(repo, "rev-parse", "--verify", "--quiet", f"{ref}^{{commit}}")
    if found.returncode == 0:
        return found.stdout.strip()
    if _git(repo, "rev-parse", "--is-shallow-repository").stdout.strip() == "true":
        raise BaselineUnavailable("shallow-clone", f"the baseline commit {ref} is not in this shallow clone: "
                                                   "`git fetch --unshallow` brings the history")
    raise BaselineUnavailable("unknown-ref", f"{ref} names no commit of {repo}")


def cache_root() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "gpnarx" / "bench-baseline"


def export(ref: str, repo: Path = ROOT, cache: Path | None = None) -> Path:
    """The folder holding ``model/`` of ``ref``'s commit (exported on first use); BaselineUnavailable if absent."""
    commit = resolve(ref, repo)
    dest = (cache or cache_root()) / commit
    if (dest / "model" / "__init__.py").is_file():
        return dest
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{commit[:12]}-", dir=dest.parent))
    try:
        proc = subprocess.run(["git", "-C", str(repo), "archive", "--format=tar", commit, "model"],
                              capture_output=True, check=False)
        if proc.returncode != 0:
            raise BaselineUnavailable("no-model", f"git archive {commit} model failed: "
                                                  f"{proc.stderr.decode(errors='replace').strip()}")
        with tarfile.open(fileobj=io.BytesIO(proc.stdout)) as tar:
            tar.extractall(tmp, filter="data")
        try:
            tmp.rename(dest)
        except OSError:  # another bench exported it first
            if not (dest / "model" / "__init__.py").is_file():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return dest


def export_package(ref: str, repo: Path = ROOT, cache: Path | None = None) -> Path:
    """A folder to put first on PYTHONPATH so that ``import gpnarx`` in a new process is the whole package as it
    stood at ``ref`` (exported on first use): ``gpnarx/`` of that commit with every folder its pyproject.toml maps
    into the package (``[tool.setuptools.package-dir]``: ``model/`` as ``gpnarx/model``, ...) inside it. For
    benches whose baseline is a whole ``gpnarx`` process; BaselineUnavailable where the commit is absent."""
    import tomllib

    commit = resolve(ref, repo)
    dest = (cache or cache_root()) / f"{commit}-package"
    if (dest / "gpnarx" / "__init__.py").is_file():
        return dest
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{commit[:12]}-pkg-", dir=dest.parent))
    try:
        proc = subprocess.run(["git", "-C", str(repo), "archive", "--format=tar", commit], capture_output=True,
                              check=False)
        if proc.returncode != 0:
            raise BaselineUnavailable("no-tree", f"git archive {commit} failed: "
                                                 f"{proc.stderr.decode(errors='replace').strip()}")
        src = tmp / "src"
        with tarfile.open(fileobj=io.BytesIO(proc.stdout)) as tar:
            tar.extractall(src, filter="data")
        mapping = tomllib.loads((src / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
        site = tmp / "site"
        shutil.copytree(src / mapping.get("gpnarx", "gpnarx"), site / "gpnarx")
        for name, folder in mapping.items():
            parts = name.split(".")
            if len(parts) == 2 and parts[0] == "gpnarx":  # nested packages come with their parent's folder
                shutil.copytree(src / folder, site / "gpnarx" / parts[1], dirs_exist_ok=True)
        try:
            site.rename(dest)
        except OSError:  # another bench exported it first
            if not (dest / "gpnarx" / "__init__.py").is_file():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return dest


_ABSOLUTE = re.compile(r"^\s*(from|import)\s+gpnarx\b", re.M)


def load_model(ref: str = MC_BASELINE, repo: Path = ROOT, cache: Path | None = None):
    """The baseline's ``model`` package, imported as ``_baseline_<commit12>`` (its submodules on demand:
    ``importlib.import_module(pkg.__name__ + ".freerun")``, or ``submodule(pkg, "freerun")``)."""
    folder = export(ref, repo, cache) / "model"
    name = f"_baseline_{folder.parent.name[:12]}"
    if name in sys.modules:
        return sys.modules[name]
    for path in sorted(folder.rglob("*.py")):
        if _ABSOLUTE.search(path.read_text()):
            raise BaselineUnavailable("not-standalone", f"{path.relative_to(folder.parent)} imports gpnarx by name: "
                                                        "it would run the product's code, not the baseline's")
    spec = importlib.util.spec_from_file_location(name, folder / "__init__.py",
                                                  submodule_search_locations=[str(folder)])
    pkg = importlib.util.module_from_spec(spec)
    sys.modules[name] = pkg
    spec.loader.exec_module(pkg)
    return pkg


def submodule(pkg, name: str):
    """``pkg.NAME`` of a baseline package (``load_model``)."""
    return importlib.import_module(f"{pkg.__name__}.{name}")


def fitted_copy(pkg, model):
    """The product's fitted ``model`` as the baseline's own estimator: the same posterior, read through the
    bundle contract (the description as JSON, the arrays as they are)."""
    description = json.loads(json.dumps(model.fitted_description()))
    try:
        return submodule(pkg, "estimator").GPNARX.from_fitted(description, dict(model.fitted_arrays()))
    except (KeyError, TypeError, ValueError) as exc:
        raise BaselineUnavailable("incompatible", f"the baseline cannot read the product's fitted model "
                                                  f"({type(exc).__name__}: {exc})") from None
