"""Registry writes are atomic: a bundle write killed midway leaves no partial version visible.

A separate Python process re-saves a bundle of the test registry with ``storage.bundle.save_bundle``
whose writes are slowed down at one stage (while writing the arrays, or with everything written
but before the final rename); once the hidden temporary folder exists and holds files, the process
is killed with SIGKILL. Then ``Registry.scan``, ``next_version``, and the service's
``/v1/models``, ``/v1/models/{name}`` and ``/health/ready`` must show exactly the bundles of
before (no new version, no refused entry for the leftover); a later write of the same version
succeeds; and the documented clean-up (``remove_stale_temps``, also run by ``save_bundle`` for
folders older than ``STALE_TMP_SECONDS``) removes stale leftovers but never a fresh one.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from test_service_support import FS, built_registry, copy_registry

from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings
from gpnarx.storage.bundle import STALE_TMP_SECONDS, next_version, remove_stale_temps, save_bundle
from gpnarx.storage.registry import Registry

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")

# The writer: loads boucwen/1 and saves it as NAME:VERSION with one stage made slow. It prints
# "STALLED" once the slow stage is reached (files are already in the temporary folder), then sleeps.
WRITER = textwrap.dedent("""
    import sys, time
    import numpy as np
    import gpnarx.storage.bundle as mb

    root, name, version, stage = sys.argv[1:5]
    bundle = mb.load_bundle(f"{root}/boucwen/1")
    calls = {"n": 0}

    def stall():
        print("STALLED", flush=True)
        time.sleep(120)

    if stage == "arrays":  # killed in the middle of the array files
        real_save = np.save

        def slow_save(path, arr, **kw):
            real_save(path, arr, **kw)
            calls["n"] += 1
            if calls["n"] == 2:
                stall()

        mb.np.save = slow_save
    elif stage == "rename":  # every file written, manifest included; killed just before the rename
        real_rename = mb.os.rename

        def slow_rename(src, dst):
            stall()
            real_rename(src, dst)

        mb.os.rename = slow_rename
    m = bundle.manifest
    mb.save_bundle(bundle.model, root, name, version, fs=m["fs"], units=m["units"], physics=m["physics"],
                   novelty=m["novelty"], training=m["training"])
    print("DONE", flush=True)
""")


def _kill_midway(root: Path, name: str, version: str, stage: str) -> Path:
    """Run the writer, SIGKILL it at ``stage``; returns the leftover temporary folder."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(root), name, version, stage], cwd=str(ROOT),
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline().strip()
        assert line == "STALLED", f"writer did not stall: {line!r} {proc.stderr.read() if proc.poll() else ''}"
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:  # pragma: no cover
            proc.kill()
            proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    leftovers = [p for p in (root / name).iterdir() if p.name.startswith(f".tmp-{version}-")]
    assert len(leftovers) == 1, leftovers
    tmp = leftovers[0]
    files = {p.name for p in tmp.iterdir()}
    if stage == "arrays":
        assert len([f for f in files if f.endswith(".npy")]) == 2 and "manifest.json" not in files, files
    else:  # a complete bundle, only not renamed into place
        assert {"manifest.json", "manifest.sha256", "theta.npy"} <= files, files
    assert not (root / name / version).exists()
    return tmp


def _visible(root: Path) -> tuple[dict, list]:
    reg = Registry(root).scan()
    return {n: reg.versions(n) for n in reg.names()}, reg.refused


def _service_view(root: Path) -> tuple[dict, dict, dict]:
    c = TestClient(create_app(root, Settings(workers=1, queue_size=1)), raise_server_exceptions=False)
    models = {m["name"]: m["versions"] for m in c.get("/v1/models").json()["models"]}
    ready = c.get("/health/ready").json()
    detail = c.get("/v1/models/boucwen").json()
    return models, ready, detail


@pytest.mark.parametrize("stage", ["arrays", "rename"])
def test_killed_write_leaves_no_partial_version(tmp_path, stage):
    root = copy_registry(tmp_path / "reg")
    before = _visible(root)
    assert before == ({"boucwen": ["1", "2"], "plain": ["1"]}, [])

    tmp = _kill_midway(root, "boucwen", "3", stage)
    # storage.bundle: nothing new, nothing refused, the next version is still 3
    assert _visible(root) == before
    assert next_version(root, "boucwen") == "3"
    # the service: model list, model detail and readiness show the same bundles, no refused entry
    models, ready, detail = _service_view(root)
    assert models == {"boucwen": ["1", "2"], "plain": ["1"]}
    assert ready["models"] == models and ready["refused"] == [] and ready["bundles"] == 3
    assert detail["version"] == "2" and detail["versions"] == ["1", "2"]
    # the service's start removed the leftover at once: its writer process is gone (bundle.writer_tag)
    assert not tmp.exists()
    # a fresh leftover of an unknown writer (another host, or an older package) is not removed by the next
    # write (it could be a write in progress) ...
    tmp = root / "boucwen" / ".tmp-3-unknown"
    tmp.mkdir()
    save_bundle(built_registry().model, root, "boucwen", "3", fs=FS, units={"u": "N", "y": "m"}, training={})
    assert tmp.is_dir()
    assert _visible(root) == ({"boucwen": ["1", "2", "3"], "plain": ["1"]}, [])
    # ... a stale one is, by the next write of that model and by remove_stale_temps
    old = time.time() - STALE_TMP_SECONDS - 60
    os.utime(tmp, (old, old))
    save_bundle(built_registry().model, root, "boucwen", "4", fs=FS, units={"u": "N", "y": "m"}, training={})
    assert not tmp.exists()
    assert _visible(root) == ({"boucwen": ["1", "2", "3", "4"], "plain": ["1"]}, [])


def test_killed_first_write_of_a_new_model_is_invisible(tmp_path):
    root = copy_registry(tmp_path / "reg")
    tmp = _kill_midway(root, "newmodel", "1", "rename")
    assert _visible(root) == ({"boucwen": ["1", "2"], "plain": ["1"]}, [])
    models, ready, _ = _service_view(root)
    assert "newmodel" not in models and ready["refused"] == []
    c = TestClient(create_app(root, Settings(workers=1, queue_size=1)), raise_server_exceptions=False)
    r = c.get("/v1/models/newmodel")
    assert r.status_code == 404 and r.json()["field"] == "name"
    assert not tmp.exists()  # removed by the service's start: its writer process is gone
    # explicit clean-up: a fresh leftover of an unknown writer survives a threshold, not a zero threshold
    tmp = root / "newmodel" / ".tmp-1-unknown"
    tmp.mkdir()
    assert remove_stale_temps(root) == [] and tmp.is_dir()
    assert remove_stale_temps(root, 0) == [tmp] and not tmp.exists()
    assert next_version(root, "newmodel") == "1"


def test_schema_1_manifest_is_migrated_and_a_future_schema_refused(tmp_path):
    """Bundles carry a schema version; older ones are migrated by explicit steps, newer ones refused."""
    import hashlib
    import json

    from gpnarx.storage.bundle import SCHEMA_VERSION, BundleError, load_bundle, migrate_manifest

    m1 = {"schema_version": 1, "estimator": {"n_inducing": 64}}
    out = migrate_manifest(m1)
    assert out["schema_version"] == SCHEMA_VERSION == 2 and out["schema_version_written"] == 1
    assert out["estimator"]["constant_cap"] is None and out["legacy"] == ["no_constant_cap"]
    assert out["estimator"]["n_inducing"] == 64 and out["training_envelope"] is None and out["n_train"] == 0
    for bad in (0, 3, "2", True, None):
        with pytest.raises(BundleError, match="schema_version"):
            migrate_manifest({"schema_version": bad, "estimator": {}})
    # on disk: a saved bundle rewritten as schema 1 without the later keys loads, a schema 99 one is refused
    src = copy_registry(tmp_path / "reg") / "plain" / "1"
    mf = src / "manifest.json"
    man = json.loads(mf.read_text())
    assert man["schema_version"] == SCHEMA_VERSION
    for k in ("training_envelope", "noise_calibration", "nlml", "n_train"):
        man.pop(k, None)
    man["estimator"].pop("constant_cap")
    for version, ok in ((1, True), (99, False)):
        man["schema_version"] = version
        mf.write_text(json.dumps(man))
        (src / "manifest.sha256").write_text(hashlib.sha256(mf.read_bytes()).hexdigest() + "\n")
        if ok:
            b = load_bundle(src)
            assert b.model.envelope_ is None and b.manifest["schema_version_written"] == 1
        else:
            with pytest.raises(BundleError, match="schema_version 99 is not supported"):
                load_bundle(src)
