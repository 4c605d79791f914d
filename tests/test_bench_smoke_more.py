"""The other half of tests/test_bench_smoke.py's bench scripts in --quick mode (every other script), in a
module of its own so that pytest-xdist runs the two halves on two workers."""
from __future__ import annotations

import pytest
from test_bench_smoke import SCRIPTS, run_quick

THERE = SCRIPTS[1::2]


@pytest.mark.parametrize("script", THERE)
def test_bench_quick(script):
    run_quick(script)


def test_bench_memory_pipeline_quick():
    """bench_memory.py --pipeline --quick: whole gpnarx processes (train, predict, Monte Carlo predict); train's peak
    RSS against the held-out calibration in one call over every row, and the two bundles' numbers."""
    import subprocess
    import sys

    from test_bench_smoke import ROOT, check_contract, parse_result

    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_memory.py"), "--pipeline", "--quick",
                           "--threads", "1"], cwd=ROOT, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, f"exited {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr[-3000:]}"
    kv = parse_result(proc.stdout)
    check_contract(kv)
    for key in ("train_peak_mib", "predict_peak_mib", "mc_peak_mib", "train_tree_pss_mib"):
        assert float(kv[key]) > 0, kv
    assert int(kv["within_limit"]) == 1, kv
    # the row blocks bound the calibration's memory (one call: K of 45 k rows x 400 points and its temporaries)
    assert float(kv["ratio"]) > 1.5, kv
    assert float(kv["bundle_max_rel_diff"]) < 1e-12, kv  # and change no number beyond round-off
