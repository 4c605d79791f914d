"""bench/baseline.py: a bench's frozen baseline is earlier product code taken from the git history (not a copy in
the tree), and a clone without that history (a shallow clone) skips the baseline with a reason, not a crash."""
from __future__ import annotations

import importlib.util
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _baseline():
    spec = importlib.util.spec_from_file_location("bench_baseline", ROOT / "bench" / "baseline.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_a_shallow_clone_says_why_it_has_no_baseline(tmp_path):
    B = _baseline()
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", "--depth", "1", "--no-checkout", ROOT.as_uri(), str(clone)], check=True)
    with pytest.raises(B.BaselineUnavailable) as exc:
        B.export(B.MC_BASELINE, clone, cache=tmp_path / "cache")
    assert exc.value.code == "shallow-clone" and "git fetch --unshallow" in str(exc.value)
    assert not (tmp_path / "cache").exists()


def test_an_unknown_ref_or_a_folder_outside_git_is_refused(tmp_path):
    B = _baseline()
    with pytest.raises(B.BaselineUnavailable) as exc:
        B.resolve("no-such-ref-" + "0" * 8, ROOT)
    assert exc.value.code in ("unknown-ref", "shallow-clone")
    with pytest.raises(B.BaselineUnavailable) as exc:
        B.resolve(B.MC_BASELINE, tmp_path)
    assert exc.value.code == "not-a-checkout"


def test_the_baseline_is_the_commits_model_under_a_name_of_its_own(tmp_path):
    B = _baseline()
    try:
        commit = B.resolve(B.MC_BASELINE, ROOT)
    except B.BaselineUnavailable as exc:
        pytest.skip(f"no baseline in this clone ({exc.code}): {exc}")
    pkg = B.load_model(B.MC_BASELINE, ROOT, cache=tmp_path)
    assert pkg.__name__ == f"_baseline_{commit[:12]}" and (tmp_path / commit / "model" / "__init__.py").is_file()
    freerun = B.submodule(pkg, "freerun")
    assert freerun.__name__.startswith(pkg.__name__) and Path(freerun.__file__).is_relative_to(tmp_path)
    shown = subprocess.run(["git", "-C", str(ROOT), "show", f"{commit}:model/freerun.py"], capture_output=True,
                           text=True, check=True).stdout
    assert Path(freerun.__file__).read_text() == shown
