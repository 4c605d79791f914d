"""bench/bench_streams.py with two replicas behind one address (--replicas 2, quick): the round-robin proxy hands
connections to both `gpnarx serve` processes, streams continue across them from their state tokens (one
GPNARX_STREAM_KEY), and every chunk is answered; and the novelty stream (--operation novelty) in the same mode."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _result(stdout: str) -> dict:
    lines = [ln for ln in stdout.splitlines() if ln.startswith("RESULT ")]
    assert len(lines) == 1, stdout
    return dict(tok.split("=", 1) for tok in lines[0][len("RESULT "):].split() if "=" in tok)


@pytest.mark.parametrize("operation", ["predict", "novelty"])
def test_bench_streams_two_replicas_quick(operation):
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_streams.py"), "--quick", "--replicas", "2",
                           "--operation", operation, "--streams", "2"], cwd=ROOT, capture_output=True, text=True,
                          timeout=300, check=False)
    assert proc.returncode == 0, f"exited {proc.returncode}\n{proc.stdout}\n{proc.stderr[-3000:]}"
    kv = _result(proc.stdout)
    assert kv["replicas"] == "2" and kv["operation"] == operation, kv
    assert kv["baseline_what"].startswith("replicas-x-"), kv
    both = [int(c) for c in kv["connections"].split("/")]
    assert len(both) == 2 and min(both) >= 1, kv  # both replicas served
    assert int(kv["streams"]) >= 1, kv  # every chunk of a stream answered 200 across the replicas
