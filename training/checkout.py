"""The repository's study scripts (``studies/``), which the wheel does not ship.

``gpnarx reproduce STUDY -- ARGS`` and the protocols that use a study (``bert-real``: the every-record
table, ``studies.real_table``; ``bert-real-paper``: the receptance FRFs, ``studies.frf_check``) load them
from the checkout this package runs from: an editable install (``pip install -e .``) or the repository
root on ``sys.path``. From an installed wheel there is no ``studies/`` and the error says so.
"""
from __future__ import annotations

import importlib
import sys
from pathlib import Path
from types import ModuleType

# gpnarx reproduce's names of the runnable studies -> their modules in studies/ (each has main(argv) -> int)
STUDIES = {
    "cycle-study": "cycle_study",
    "torque-study": "torque_study",
    "real-monitor-study": "real_monitor_study",
    "split-study": "split_study",
    "rows-study": "rows_study",
    "exact-study": "exact_study",
    "accelerator-page": "accelerator_page",
}


class CheckoutRequired(RuntimeError):
    """A study was asked for where no repository checkout (with its ``studies/`` folder) is found."""


def checkout_root() -> Path | None:
    """The repository root holding ``studies/`` next to this package's folder, or None (installed wheel)."""
    root = Path(__file__).resolve().parents[1]
    return root if (root / "studies" / "__init__.py").is_file() else None


def load_study(module: str) -> ModuleType:
    """``studies.MODULE`` from the checkout; CheckoutRequired where the package runs from a wheel."""
    try:
        return importlib.import_module(f"studies.{module}")
    except ModuleNotFoundError as e:
        if e.name not in ("studies", f"studies.{module}"):
            raise
    root = checkout_root()
    if root is None:
        raise CheckoutRequired(
            f"the study {module!r} lives in the repository's studies/ folder, which the installed package does "
            "not ship: run it from a checkout of the gpnarx repository (pip install -e . there)")
    if str(root) not in sys.path:
        sys.path.append(str(root))
    return importlib.import_module(f"studies.{module}")


def call_study(module: str, function: str, *args, **kwargs):
    """``studies.MODULE.FUNCTION(*args, **kwargs)``, as a task for a worker process: the task names this
    package's function and the study by strings, so a worker started without the checkout on its path
    (a joblib/loky worker of the ``gpnarx`` command) can unpickle it; ``load_study`` finds the checkout there."""
    return getattr(load_study(module), function)(*args, **kwargs)


def run_study(name: str, argv: list[str]) -> int:
    """Run the study ``name`` (a key of STUDIES) with its own command-line arguments; its exit code."""
    return int(load_study(STUDIES[name]).main(list(argv)) or 0)
