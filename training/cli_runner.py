"""Run a ``gpnarx`` command as a user would, in a child process, and return its ``--json`` answer.

The study scripts in ``gpnarx.training`` drive the CLI end to end (simulate, train, calibrate,
loops) so their figures come from the same code path a user runs; a child process keeps the
dependency rule (training never imports the CLI package, which sits on top of it).
"""
from __future__ import annotations

import json
import subprocess
import sys


def run_cli(argv: list[str]) -> dict:
    """``python -m gpnarx --json ARGV``; the JSON object it prints, or RuntimeError with its error line."""
    proc = subprocess.run([sys.executable, "-m", "gpnarx", "--json", *map(str, argv)], capture_output=True,
                          text=True, check=False)
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or [""])[-1]
        raise RuntimeError(f"gpnarx {' '.join(map(str, argv))} failed (exit {proc.returncode}): {last}")
    return json.loads(proc.stdout)
