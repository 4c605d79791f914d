"""tools/fault_probes.py runs against a real ``gpnarx serve`` and prints its RESULT line (the Host-header
probe, the quickest; the stored run of all seven is docs/runs/faults/probes.txt)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from test_service_support import built_registry

ROOT = Path(__file__).resolve().parents[1]


def test_host_header_probe_runs_and_reports():
    proc = subprocess.run([sys.executable, str(ROOT / "tools" / "fault_probes.py"), "--registry",
                           str(built_registry().root), "--only", "5"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    assert len(lines) == 1, proc.stdout
    kv = dict(tok.split("=", 1) for tok in lines[0].split()[1:])
    assert kv["probe"] == "5" and kv["status"] == "404" and kv["location"] == "none", kv
    assert kv["type"] == "application/problem+json" and kv["before"].startswith("307"), kv


def test_stored_run_holds_all_seven_probes():
    text = (ROOT / "docs" / "runs" / "faults" / "probes.txt").read_text()
    probes = [ln.split()[1] for ln in text.splitlines() if ln.startswith("RESULT ")]
    assert probes == [f"probe={k}" for k in range(1, 8)], probes
