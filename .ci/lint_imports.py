"""Run import-linter (the contracts in pyproject.toml [tool.importlinter]) on the gpnarx package.

import-linter finds a package's modules by walking its folder, but the repository maps separate
top-level folders into ``gpnarx`` (setuptools ``package-dir``: ``model/`` is ``gpnarx.model``, ...),
and ``gpnarx/`` on disk holds only the root. So this script lays the installed shape out in a
temporary folder of symbolic links, one per ``package-dir`` entry, puts it first on ``sys.path`` and
runs ``lint-imports`` against it. Usage: ``python .ci/lint_imports.py [lint-imports options]``.
"""
from __future__ import annotations

import os
import sys
import tempfile
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def package_tree(dest: Path) -> Path:
    """Symlink the package-dir mapping of pyproject.toml under ``dest``; returns ``dest``."""
    setup = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    mapping = setup["package-dir"]
    for package in sorted(mapping, key=lambda p: p.count(".")):
        target = dest.joinpath(*package.split("."))
        if target.exists():  # a subpackage whose folder already sits inside its parent's link
            if target.resolve() != (ROOT / mapping[package]).resolve():
                raise SystemExit(f"package-dir {package} -> {mapping[package]} is not inside its parent's folder")
            continue
        if "." not in package:  # the root: a real folder whose files are links (subpackages go beside them)
            target.mkdir(parents=True)
            for f in (ROOT / mapping[package]).glob("*.py"):
                (target / f.name).symlink_to(f)
        else:
            target.symlink_to(ROOT / mapping[package], target_is_directory=True)
    return dest


def main(argv: list[str]) -> int:
    with tempfile.TemporaryDirectory(prefix="gpnarx-lint-imports-") as tmp:
        sys.path.insert(0, str(package_tree(Path(tmp))))
        from importlinter.cli import lint_imports

        os.chdir(tmp)  # lint-imports puts the working folder on sys.path: the checkout's gpnarx/ must not win
        return lint_imports(config_filenames=(str(ROOT / "pyproject.toml"),), no_cache=True, no_logo=True,
                            verbose="--verbose" in argv, show_timings="--show-timings" in argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
