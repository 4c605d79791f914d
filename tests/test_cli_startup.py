"""What a one-shot CLI command pays before it computes: its imports, and the BLAS limit it sets.

``gpnarx predict`` on a whole record is a few seconds, so half a second of imports is a large share of it
(bench/bench_realtime.py times the whole process). Each test runs in a fresh interpreter, as a command does.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

# modules the predict path must not import: scikit-learn (the estimator follows its protocol without it,
# model.params), scipy.signal / scipy.stats (half a second together; the frequency check's STFT is numpy's) and
# scipy.special (a tenth of a second; the band's z is the standard library's, model.normal)
HEAVY = ("sklearn", "scipy.stats", "scipy.signal", "scipy.ndimage", "scipy.special")


def _fresh(code: str, **env) -> str:
    """stdout of ``code`` run by a fresh interpreter with ``env`` added to this process's environment."""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={**os.environ, **env})
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_the_predict_path_imports_no_heavy_module():
    """Everything ``gpnarx predict`` imports to load a bundle, run it and check the envelope."""
    code = (
        "import sys, json, numpy as np\n"
        "import gpnarx.cli.main, gpnarx.cli.cmd_predict, gpnarx.storage.bundle, gpnarx.storage.registry\n"
        "import gpnarx.storage.record_files, gpnarx.operations\n"
        "from gpnarx.model.envelope import band_envelope, frequency_share\n"
        "u = np.sin(np.arange(4096) * 0.3)\n"
        "frequency_share(band_envelope([u]), u)\n"
        f"print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))\n"
    )
    assert json.loads(_fresh(code)) == []


def test_blas_limit_set_before_any_import_holds_for_scipys_blas():
    """``tune_for_free_run`` called first thing (before scipy is imported) limits scipy's BLAS too:
    threadpoolctl limits only loaded libraries, and scipy's OpenBLAS is a separate one from numpy's."""
    code = (
        "import json\n"
        "from gpnarx.runtime import tune_for_free_run\n"
        "tune_for_free_run(1)\n"
        "import scipy.linalg\n"
        "from threadpoolctl import threadpool_info\n"
        "print(json.dumps([(i['filepath'], i['num_threads']) for i in threadpool_info() if i['user_api'] == 'blas']))\n"
    )
    # the suite's conftest sets one thread by environment; the child starts both libraries at two
    libs = json.loads(_fresh(code, OPENBLAS_NUM_THREADS="2"))
    assert len(libs) >= 2, libs  # numpy's and scipy's
    assert all(n == 1 for _, n in libs), libs
