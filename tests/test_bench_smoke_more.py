"""The other half of tests/test_bench_smoke.py's bench scripts in --quick mode (every other script), in a
module of its own so that pytest-xdist runs the two halves on two workers."""
from __future__ import annotations

import pytest
from test_bench_smoke import SCRIPTS, run_quick

THERE = SCRIPTS[1::2]


@pytest.mark.parametrize("script", THERE)
def test_bench_quick(script):
    run_quick(script)
