"""The kernels' numbers are the product's: every contract method of every shipped kernel, ML-II's NLML and
gradient, the sparse bound and the free runs of a small GPNARX per kernel spec equal the reference numbers
of tests/data/kernel_numbers.json (written by tests/data/kernel_numbers.py on the code before the kernels'
refactor) to 1e-12 relative (normwise per array; the sparse bound to its own round-off floor where that is
larger), and ML-II refits the recorded hyperparameters."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).with_name("data")
sys.path.insert(0, str(DATA))
import kernel_numbers as ref  # noqa: E402

REF = json.loads((DATA / "kernel_numbers.json").read_text())
RTOL = 1e-12


def _rectangular(x) -> bool:
    """Whether nested lists ``x`` are one numeric array."""
    try:
        return np.asarray(x, dtype=float).dtype == float
    except (ValueError, TypeError):
        return False


def _walk(new, old, where, out):
    """(where, max relative difference) for every array/number of ``old``, compared with ``new``."""
    if isinstance(old, dict):
        assert isinstance(new, dict) and set(new) == set(old), where
        for k in old:
            _walk(new[k], old[k], f"{where}.{k}", out)
    elif old is None or new is None:
        assert old is None and new is None, where
    elif isinstance(old, list) and not _rectangular(old):
        assert isinstance(new, list) and len(new) == len(old), where
        for i, (a, b) in enumerate(zip(new, old)):
            _walk(a, b, f"{where}[{i}]", out)
    else:
        a, b = np.asarray(new, dtype=float), np.asarray(old, dtype=float)
        assert a.shape == b.shape, where
        scale = float(np.max(np.abs(b))) if b.size else 0.0
        diff = float(np.max(np.abs(a - b))) if b.size else 0.0
        out.append((where, 0.0 if diff == 0.0 else diff / max(scale, 1e-300)))


def _check(new, old, where, floor=None):
    """Every array of ``new`` equal to ``old``'s to RTOL, or to its round-off floor by name where larger."""
    found = []
    _walk(json.loads(json.dumps(new)), old, where, found)
    bad = [(w, r) for w, r in found if not r <= max(RTOL, (floor or {}).get(w.split(".", 1)[-1], 0.0))]
    assert not bad, f"{len(bad)} of {len(found)} differ beyond {RTOL}: {bad[:8]}"
    return found


@pytest.mark.parametrize("name", sorted(REF["kernels"]))
def test_every_contract_method_keeps_its_numbers(name):
    ins = ref.inputs()
    k = ref.kernels()[name]
    _check(ref.kernel_methods(k, ins["X"], ins["X2"], ins["w"], ins["beta"]), REF["kernels"][name], name)


@pytest.mark.parametrize("spec", ref.SPECS)
def test_nlml_gradient_and_sparse_bound_keep_their_numbers(spec):
    """To 1e-12, or for an ill-conditioned quantity (the sparse bound with RBF or cubic kernels) to what a
    one-ulp change of theta changes in it (``kernel_numbers.ml2_floors``, recorded with the numbers)."""
    _check(ref.ml2_numbers(spec), REF["ml2"][spec], spec, REF["ml2_floor"][spec])


@pytest.mark.parametrize("spec", ref.SPECS)
def test_fit_and_free_runs_keep_their_numbers(spec):
    """At the recorded hyperparameters the free runs are the recorded ones; ML-II refits them (to its own
    tolerance: round-off in a gradient moves the optimiser's path, not its optimum)."""
    old = REF["fits"][spec]
    new = ref.fit_numbers(spec, theta=old)
    for mode in old:
        assert new[mode]["mc_local_steps"] == old[mode]["mc_local_steps"]
        for key in ("linear_mean", "linear_std", "mc_mean", "mc_std"):
            _check(new[mode][key], old[mode][key], f"{spec}.{mode}.{key}")
    refit = ref.fit_numbers(spec)
    for mode in old:
        assert np.allclose(refit[mode]["theta"], old[mode]["theta"], rtol=1e-6, atol=1e-6)
        assert refit[mode]["nlml"] == pytest.approx(old[mode]["nlml"], rel=1e-9)
