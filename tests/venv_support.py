"""A fresh venv for the tests that install the built wheel (tests/test_wheel.py, tests/test_deploy.py).

The venv must see the dependencies of the environment the tests run in, so nothing is downloaded,
and that environment is the user's own venv as often as the machine's interpreter. ``venv``'s
``system_site_packages`` sees only the *base* interpreter's packages (``sys.base_prefix``), not the
venv the tests run in: from inside a user's venv it finds no fastapi, no scikit-learn. So the new
venv is made without system packages, and a ``.pth`` file in its site-packages lists the running
environment's site-packages folders (``site.getsitepackages()``, which in a venv made with system
packages holds the base interpreter's too). Those folders come after the venv's own on
``sys.path``, so a wheel installed into the venv answers first; ``.pth`` files inside them are not
run, so the checkout's editable install (a finder hooked in by a ``.pth`` file) stays out.
"""
from __future__ import annotations

import os
import site
import subprocess
import venv
from pathlib import Path

PTH_NAME = "_gpnarx_test_parent_env.pth"


def parent_site_dirs() -> list[str]:
    """The running environment's site-packages folders that exist, in sys.path order."""
    dirs = [d for d in site.getsitepackages() if Path(d).is_dir()]
    user = site.getusersitepackages() if site.ENABLE_USER_SITE else None
    if user and Path(user).is_dir():
        dirs.append(user)
    return list(dict.fromkeys(dirs))


def make_venv(env_dir: Path, with_pip: bool = False) -> Path:
    """Create a venv at ``env_dir`` that sees this environment's packages; returns its python."""
    venv.EnvBuilder(system_site_packages=False, with_pip=with_pip, symlinks=os.name != "nt").create(env_dir)
    py = env_dir / ("Scripts/python.exe" if os.name == "nt" else "bin/python")
    purelib = subprocess.run([str(py), "-I", "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    Path(purelib).mkdir(parents=True, exist_ok=True)
    (Path(purelib) / PTH_NAME).write_text("".join(d + "\n" for d in parent_site_dirs()))
    return py
