"""Run a ``gpnarx`` command as a user would, in a child process, and return its ``--json`` answer.

The study scripts in ``studies`` drive the CLI end to end (simulate, train, calibrate,
loops) so their figures come from the same code path a user runs, in a child process as a user's
shell would run it.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path


def run_cli(argv: list[str]) -> dict:
    """``python -m gpnarx --json ARGV``; the JSON object it prints, or RuntimeError with its error line."""
    proc = subprocess.run([sys.executable, "-m", "gpnarx", "--json", *map(str, argv)], capture_output=True,
                          text=True, check=False)
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or [""])[-1]
        raise RuntimeError(f"gpnarx {' '.join(map(str, argv))} failed (exit {proc.returncode}): {last}")
    return json.loads(proc.stdout)


def emit(result: dict, out=None, shown: dict | None = None) -> int:
    """A study's result: written as JSON to ``out`` when given, printed (``shown``, default all of it); exit 0."""
    text = json.dumps(result, indent=1)
    if out:
        Path(out).write_text(text + "\n")
    print(text if shown is None else json.dumps(shown, indent=1))
    return 0
