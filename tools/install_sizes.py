"""Install sizes: the core wheel, the core with the extra ``train`` (the core before the install tiers) and the
Docker image's Python layer, each installed from the image's lock file with hashes, offline, into a fresh venv.

    python tools/install_sizes.py [--out docs/runs/install/sizes.json] [--keep DIR]
    python tools/install_sizes.py --render docs/deploy.md      # re-render the page's table from the stored run

There is no Docker engine on the development machines, so this runs the Dockerfile's steps directly:

1. its build stage: ``pip wheel --require-hashes --no-deps -r requirements.lock -w WHEELS`` (every pin checked
   against its sha256), then ``pip wheel --no-deps . -w WHEELS`` on a copy of the files the stage copies;
2. its install step, ``pip install --no-index --find-links WHEELS SPEC`` with the image's ``SPEC`` (read from
   the Dockerfile), into a fresh venv, with the image's ``PIP_*`` and ``PYTHONDONTWRITEBYTECODE`` settings, then
   the image's import check;
3. the same install of ``gpnarx`` (the core) and ``gpnarx[train]`` into their own fresh venvs.

Each tier's figure is what it adds to an empty venv's site-packages (pip and setuptools, which the base image
has too): bytes of the files (apparent sizes, byte-compiled ``__pycache__`` included, as pip writes them) and
the packages with their versions. The image's figure is the estimate of its Python layer, on top of the base
image named in the Dockerfile's final ``FROM``; the default registry that ``gpnarx build-defaults`` writes at
image build is not included. Baseline of ``ratio=``: the core with ``train`` (the core before the tiers);
ratio = its bytes / the core's.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from gpnarx.training.pages.install_sizes import BEGIN, END, render
from gpnarx.training.pages.markdown import replace_block

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "docs" / "runs" / "install" / "sizes.json"
LOCK = ROOT / "requirements.lock"
DOCKERFILE = ROOT / "Dockerfile"
# what a fresh venv already holds (the base image's Python has them too)
BASE_PACKAGES = {"pip", "setuptools", "wheel"}
LARGEST = 8


def canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def dockerfile_facts(text: str) -> dict:
    """The base image of the final stage, the files the build stage copies and the image's install spec."""
    stages = re.split(r"^FROM\s+", text, flags=re.M)[1:]
    if len(stages) < 2:
        raise ValueError("Dockerfile: expected a build stage and a final stage")
    base = stages[-1].split()[0]
    copies = []
    for line in stages[0].splitlines():
        m = re.match(r"COPY\s+(?!--)(.+)\s+(\S+)$", line.strip())
        if m:
            copies += m.group(1).split()
    spec = re.search(r'pip install --no-index --find-links /tmp/wheels "([^"]+)"', stages[-1])
    if not spec:
        raise ValueError("Dockerfile: the final stage's `pip install --no-index --find-links` line was not found")
    return {"base_image": base, "copies": copies, "spec": spec.group(1)}


def locked() -> dict[str, str]:
    """requirements.lock's pins: {canonical name: version}."""
    pins = {}
    for line in LOCK.read_text().splitlines():
        m = re.match(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==(\S+)", line)
        if m:
            pins[canonical(m.group(1))] = m.group(2)
    return pins


def _pip(python: Path | str, *args: str, env: dict) -> None:
    proc = subprocess.run([str(python), "-m", "pip", *args], env=env, capture_output=True, text=True)
    if proc.returncode:
        raise RuntimeError(f"pip {' '.join(args)} failed ({proc.returncode}):\n{proc.stdout[-2000:]}\n"
                           f"{proc.stderr[-4000:]}")


def _site(venv: Path) -> Path:
    return next((venv / "lib").glob("python*/site-packages"))


def _files(site: Path) -> dict[str, int]:
    return {p.relative_to(site).as_posix(): p.lstat().st_size for p in site.rglob("*") if p.is_file() or p.is_symlink()}


def _packages(venv: Path, env: dict) -> dict[str, str]:
    out = subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "list", "--format=json"], env=env,
                         capture_output=True, text=True, check=True).stdout
    return {canonical(p["name"]): p["version"] for p in json.loads(out)}


def _top(rel: str) -> str:
    head = rel.split("/", 1)[0]
    return re.sub(r"(-[^-]+)?\.(dist-info|data)$|\.libs$|\.py$|\.pth$", "", head).lstrip("_")


def measure_tier(work: Path, name: str, spec: str, wheels: Path, env: dict, empty: dict) -> dict:
    venv = work / f"venv-{name}"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    _pip(venv / "bin" / "python", "install", "--no-index", "--find-links", str(wheels), spec, env=env)
    site = _site(venv)
    files = {k: v for k, v in _files(site).items() if k not in empty["files"]}
    packages = {k: v for k, v in _packages(venv, env).items() if k not in BASE_PACKAGES}
    by_top: dict[str, int] = {}
    for rel, size in files.items():
        by_top[_top(rel)] = by_top.get(_top(rel), 0) + size
    largest = sorted(by_top.items(), key=lambda kv: -kv[1])[:LARGEST]
    return {"spec": spec, "packages": dict(sorted(packages.items())), "n_packages": len(packages),
            "site_packages_bytes": sum(files.values()),
            "pycache_bytes": sum(v for k, v in files.items() if "/__pycache__/" in f"/{k}"),
            "largest": [[k, v] for k, v in largest]}


def measure(keep: Path | None = None) -> dict:
    facts = dockerfile_facts(DOCKERFILE.read_text())
    work = Path(tempfile.mkdtemp(prefix="gpnarx-sizes-")) if keep is None else keep
    if keep is not None:
        shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    # the image's pip settings; no local wheel folders or caches: every wheel comes from the lock's hashes
    env = {k: v for k, v in os.environ.items() if not k.startswith("PIP_") and k != "PYTHONDONTWRITEBYTECODE"}
    env.update(PIP_NO_CACHE_DIR="1", PIP_DISABLE_PIP_VERSION_CHECK="1", PYTHONDONTWRITEBYTECODE="1")
    try:
        src, wheels = work / "src", work / "wheels"
        src.mkdir()
        for rel in facts["copies"]:
            p = ROOT / rel
            if p.is_dir():
                shutil.copytree(p, src / rel, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
            else:
                shutil.copy2(p, src / rel)
        # the build stage, as the Dockerfile runs it
        _pip(sys.executable, "wheel", "--require-hashes", "--no-deps", "-r", str(src / "requirements.lock"),
             "-w", str(wheels), env=env)
        _pip(sys.executable, "wheel", "--no-deps", str(src), "-w", str(wheels), env=env)
        empty_venv = work / "venv-empty"
        subprocess.run([sys.executable, "-m", "venv", str(empty_venv)], check=True)
        empty = {"files": _files(_site(empty_venv))}
        tiers = {"core": measure_tier(work, "core", "gpnarx", wheels, env, empty),
                 "train": measure_tier(work, "train", "gpnarx[train]", wheels, env, empty),
                 "image": measure_tier(work, "image", facts["spec"], wheels, env, empty)}
        # the image's own check after its install step
        # (from the work folder: a checkout's gpnarx/ folder in the current directory would shadow the install)
        subprocess.run([str(work / "venv-image" / "bin" / "python"), "-c",
                        "import gpnarx.service.app, gpnarx.storage.bundle, gpnarx.cli.main"], env=env, check=True,
                       cwd=work)
        wheel_bytes = sum(p.stat().st_size for p in wheels.glob("*.whl"))
    finally:
        if keep is None:
            shutil.rmtree(work, ignore_errors=True)
    return {"base_image": facts["base_image"], "image_spec": facts["spec"],
            "lock_sha256": hashlib.sha256(LOCK.read_bytes()).hexdigest(), "lock_pins": len(locked()),
            "wheels_bytes": wheel_bytes, "python": platform.python_version(), "machine": platform.machine(),
            "pip": subprocess.run([sys.executable, "-m", "pip", "--version"], capture_output=True,
                                  text=True).stdout.split()[1],
            "tiers": tiers}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=RUN,
                    help="where to store the run (default docs/runs/install/sizes.json)")
    ap.add_argument("--keep", type=Path, default=None,
                    help="work folder to keep (wheels, venvs); default a temporary one")
    ap.add_argument("--render", type=Path, default=None, metavar="PAGE",
                    help="only re-render PAGE's install-sizes block from the stored run")
    args = ap.parse_args(argv)
    if args.render:
        run = json.loads(args.out.read_text())
        args.render.write_text(replace_block(args.render.read_text(), BEGIN, END, render(run)))
        return 0
    run = measure(args.keep)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(run, indent=1, sort_keys=True) + "\n")
    t = run["tiers"]
    print(render(run))
    print(f"RESULT core_bytes={t['core']['site_packages_bytes']} core_packages={t['core']['n_packages']} "
          f"train_bytes={t['train']['site_packages_bytes']} train_packages={t['train']['n_packages']} "
          f"image_bytes={t['image']['site_packages_bytes']} image_packages={t['image']['n_packages']} "
          f"wheels_bytes={run['wheels_bytes']} baseline={t['train']['site_packages_bytes']} "
          f"baseline_what=core_with_train_site_packages_bytes "
          f"ratio={t['train']['site_packages_bytes'] / t['core']['site_packages_bytes']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
