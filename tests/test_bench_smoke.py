"""Smoke test of the benchmarks: each bench/ script runs in --quick mode and prints the contract line.

Contract (design.md): one line starting ``RESULT `` with key=value pairs, among them the product's
figure, the baseline's and ``ratio=`` (a finite number). Runs with ``--threads 1`` so a machine
oversubscribed by other processes does not make single small BLAS calls wait for a second thread.
"""
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ["bench_freerun.py", "bench_fit.py", "bench_modes.py", "bench_scaling.py", "bench_memory.py"]


def parse_result(stdout: str) -> dict:
    lines = [ln for ln in stdout.splitlines() if ln.startswith("RESULT ")]
    assert len(lines) == 1, f"expected exactly one RESULT line, got {len(lines)}:\n{stdout}"
    pairs = {}
    for tok in lines[0][len("RESULT "):].split():
        assert "=" in tok, f"token {tok!r} is not key=value"
        k, v = tok.split("=", 1)
        pairs[k] = v
    return pairs


@pytest.mark.parametrize("script", SCRIPTS)
def test_bench_quick(script):
    path = ROOT / "bench" / script
    assert path.exists(), path
    proc = subprocess.run([sys.executable, str(path), "--quick", "--threads", "1"], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, f"{script} exited {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    kv = parse_result(proc.stdout)
    assert "ratio" in kv and "baseline" in kv, kv
    ratio = float(kv["ratio"])
    assert math.isfinite(ratio) and ratio > 0, kv
    assert math.isfinite(float(kv["baseline"])), kv


def test_parse_result_rejects_garbage():
    with pytest.raises(AssertionError):
        parse_result("no result here")
    assert parse_result("table\nRESULT a=1 ratio=2.5 baseline=3\n")["ratio"] == "2.5"
