"""A registry on object storage served by several replicas (issue 26).

The main test starts moto's S3 server on loopback (a free port, dummy credentials, the endpoint
given to every process by ``AWS_ENDPOINT_URL``), trains a small Bouc-Wen bundle into
``s3://BUCKET/plant-a`` with ``gpnarx train``, serves it with two ``gpnarx serve`` processes (each
with its own cache folder, polling every ``POLL`` s), and checks: identical answers from both
replicas for one request and seed; a new version published meanwhile is served by both within
the poll interval (the pick-up times are printed); objects of a version whose manifest is absent
are not listed; an alias set with ``gpnarx alias set`` reaches both; an object of version 1
overwritten in the bucket makes both replicas refuse version 1 (404, and its alias with it) while
version 2 keeps answering exactly as before. The other tests use fsspec's in-memory filesystem
(``memory://``) for the publish order, stale writes, the bounded cache of built models and the CLI.
"""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
import warnings
from pathlib import Path

import httpx
import numpy as np
import pytest

from gpnarx.storage.bundle import BundleError, save_bundle
from gpnarx.storage.registry import Registry, parse_model_ref, write_aliases

ROOT = Path(__file__).resolve().parents[1]
POLL = 1.0  # GPNARX_REGISTRY_POLL of the replicas [s]
BUCKET = "gpnarx-registry"
URL = f"s3://{BUCKET}/plant-a"
NAME = "bw-tiny"
FS = 750.0

TINY_CONFIG = f"""
name = "{NAME}"
[system]
fs = {FS}
units = {{ u = "N", y = "m" }}
output = "displacement"
[physics]
mass = 2.0
[model]
ny = 4
nu = 4
max_train_points = 300
restarts = 0
[predict]
mc_paths = 16
method = "linear"
[[records]]
name = "train-sweep"
roles = ["train"]
simulate = {{ system = "bouc-wen", excitation = "sweep", amplitude = 30.0, duration = 1.0, f0 = 20.0, f1 = 60.0 }}
noise = {{ fraction = 0.01, seed = 1 }}
[[records]]
name = "verify-sweep"
roles = ["verify"]
simulate = {{ system = "bouc-wen", excitation = "sweep", amplitude = 40.0, duration = 0.4, f0 = 20.0, f1 = 60.0 }}
"""


def _free_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def _wait(pred, timeout: float, step: float = 0.05):
    t0 = time.monotonic()
    while True:
        got = pred()
        if got:
            return time.monotonic() - t0
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"condition not met within {timeout} s")
        time.sleep(step)


def _tiny_model(seed: int):
    from gpnarx.model.estimator import GPNARX
    from gpnarx.training import excitations as ex
    from gpnarx.training.simulators.boucwen import BoucWen

    u = ex.multisine(FS, 20.0, 5.0, 150.0, 600, seed=seed)
    y = BoucWen().simulate(u)["y"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return GPNARX(ny=3, nu=3, max_train_points=200, n_restarts=0).fit([(u, y)])


# ------------------------------------------------------------------------------------------ S3 + replicas
@pytest.fixture(scope="module")
def s3(tmp_path_factory):
    pytest.importorskip("s3fs")
    server_mod = pytest.importorskip("moto.server")
    import s3fs

    server = server_mod.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    env = {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1",
           "AWS_ENDPOINT_URL": f"http://{host}:{port}", "GPNARX_CACHE": str(tmp_path_factory.mktemp("cache-test"))}
    drop = ("AWS_PROFILE", "AWS_SESSION_TOKEN", "AWS_ENDPOINT_URL_S3", "GPNARX_STORAGE_OPTIONS")
    saved = {k: os.environ.get(k) for k in (*env, *drop)}
    os.environ.update(env)
    for k in drop:
        os.environ.pop(k, None)
    s3fs.S3FileSystem.clear_instance_cache()
    fs = s3fs.S3FileSystem()
    fs.mkdir(BUCKET)
    try:
        yield fs, env
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        s3fs.S3FileSystem.clear_instance_cache()
        server.stop()


class Replica:
    """One ``gpnarx serve --registry s3://...`` process on a free loopback port."""

    def __init__(self, env: dict, cache: Path, log: Path):
        self.port = _free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        penv = {**os.environ, **env, "GPNARX_CACHE": str(cache), "GPNARX_REGISTRY_POLL": str(POLL),
                "GPNARX_WORKERS": "1", "GPNARX_MAX_LOADED": "2",
                "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
        for k in ("GPNARX_API_KEY", "GPNARX_REGISTRY"):
            penv.pop(k, None)
        self.log = log
        self.log_file = open(log, "w")
        self.proc = subprocess.Popen([sys.executable, "-m", "gpnarx", "serve", "--registry", URL, "--port",
                                      str(self.port), "--log-level", "warning"], cwd=str(ROOT), env=penv,
                                     stdout=subprocess.DEVNULL, stderr=self.log_file)
        self.client = httpx.Client(base_url=self.url, timeout=60)

    def ready(self) -> bool:
        assert self.proc.poll() is None, self.log.read_text()
        try:
            return self.client.get("/health/ready").status_code == 200
        except httpx.HTTPError:
            return False

    def get(self, path):
        return self.client.get(path)

    def post(self, path, body):
        return self.client.post(path, json=body)

    def close(self):
        self.client.close()
        self.proc.terminate()
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:  # pragma: no cover
            self.proc.kill()
        self.log_file.close()


def _metric(text: str, name: str) -> float:
    for line in text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    raise AssertionError(f"{name} not in /metrics")


def _answer(r) -> dict:
    assert r.status_code == 200, r.text
    d = r.json()
    return {k: d[k] for k in ("model", "version", "mean", "lower", "upper", "std", "fit", "rmse", "coverage")}


def test_two_replicas_on_s3_identical_answers_pick_up_new_versions_and_refuse_a_corrupt_object(s3, tmp_path):
    fs, env = s3
    t_start = time.monotonic()
    timings = {}
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(TINY_CONFIG)
    penv = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))

    # train into the bucket with the CLI (save_bundle publishes to the URL, manifest last)
    t0 = time.monotonic()
    out = subprocess.run([sys.executable, "-m", "gpnarx", "train", str(cfg), "--registry", URL, "--json"],
                         cwd=str(ROOT), env=penv, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    trained = json.loads(out.stdout)
    timings["train"] = time.monotonic() - t0
    assert trained["version"] == "1" and trained["path"] == f"{URL}/{NAME}/1"
    keys = fs.find(f"{BUCKET}/plant-a/{NAME}/1")
    assert f"{BUCKET}/plant-a/{NAME}/1/manifest.json" in keys and any("/report/" in k for k in keys)

    replicas = [Replica(env, tmp_path / f"cache-{k}", tmp_path / f"replica-{k}.log") for k in "ab"]
    try:
        t0 = time.monotonic()
        for rep in replicas:
            _wait(rep.ready, timeout=60, step=0.1)
        timings["replicas_ready"] = time.monotonic() - t0
        for rep in replicas:  # verified, listed, nothing built yet (lazy)
            m = rep.get("/metrics").text
            assert _metric(m, "gpnarx_bundles_loaded") == 1.0 and _metric(m, "gpnarx_bundles_in_memory") == 0.0
            assert rep.get(f"/v1/models/{NAME}").json()["aliases"] == {"latest": "1"}
            assert "<html" in rep.get(f"/v1/models/{NAME}/versions/1/report").text[:500].lower()

        from gpnarx.training import excitations as ex
        from gpnarx.training.simulators.boucwen import BoucWen

        u = ex.multisine(FS, 15.0, 20.0, 60.0, 300, seed=7)  # inside the training sweep's band
        y = BoucWen().simulate(u)["y"]
        # Monte Carlo named explicitly: the bundle's default method is linear, where the seed plays no part
        body = {"u": u.tolist(), "y": y.tolist(), "fs": FS, "method": "mc", "mc_paths": 64, "seed": 3}
        first = [_answer(rep.post(f"/v1/models/{NAME}/predict", body)) for rep in replicas]
        assert first[0]["version"] == "1" and first[0] == first[1]  # the same bytes from both replicas
        assert np.std(first[0]["mean"]) > 0 and first[0]["fit"] > 20.0  # a model, not noise (tiny training set)
        other_seed = _answer(replicas[0].post(f"/v1/models/{NAME}/predict", {**body, "seed": 4}))
        assert other_seed["mean"] != first[0]["mean"]  # the seed matters: equality above is not trivial
        assert _metric(replicas[0].get("/metrics").text, "gpnarx_bundles_in_memory") == 1.0

        # publish a new version (another model) while both serve; each sees it within the poll interval
        t_pub = time.monotonic()
        path = save_bundle(_tiny_model(11), URL, NAME, fs=FS, units={"u": "N", "y": "m"}, physics={"mass": 2.0})
        timings["publish"] = time.monotonic() - t_pub
        assert str(path) == f"{URL}/{NAME}/2" and path.name == "2"
        t_pub = time.monotonic()
        for k, rep in enumerate(replicas):
            _wait(lambda rep=rep: rep.get(f"/v1/models/{NAME}").json()["versions"] == ["1", "2"], timeout=30)
            timings[f"pickup_{'ab'[k]}"] = time.monotonic() - t_pub
        # a listing happens every POLL s; checking the new version's objects adds a little
        assert max(timings["pickup_a"], timings["pickup_b"]) < POLL + 5.0, timings
        second = [_answer(rep.post(f"/v1/models/{NAME}/predict", body)) for rep in replicas]
        assert second[0]["version"] == "2" and second[0] == second[1] and second[0]["mean"] != first[0]["mean"]
        again = _answer(replicas[1].post(f"/v1/models/{NAME}/versions/1/predict", body))
        assert again == first[0]  # version 1 pinned: the same answer as before the new version

        # objects of a version whose manifest is absent (a write in progress) are not listed
        fs.pipe(f"{BUCKET}/plant-a/{NAME}/3/theta.npy", b"partial")
        # an operator moves the production alias (CLI, one atomic object); both replicas follow
        out = subprocess.run([sys.executable, "-m", "gpnarx", "alias", "set", "--registry", URL, NAME, "production",
                              "1", "--json"], cwd=str(ROOT), env=penv, capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        assert json.loads(out.stdout) == {"name": NAME, "alias": "production", "version": "1", "previous": None}
        t_alias = time.monotonic()
        for rep in replicas:
            _wait(lambda rep=rep: rep.get(f"/v1/models/{NAME}").json()["aliases"].get("production") == "1",
                  timeout=30)
        timings["alias_pickup"] = time.monotonic() - t_alias
        for rep in replicas:
            assert rep.get("/health/ready").json()["models"] == {NAME: ["1", "2"]}
            assert rep.get("/health/ready").json()["refused"] == []
            assert _answer(rep.post(f"/v1/models/{NAME}/versions/production/predict", body)) == first[0]
            batch = rep.client.post("/v1/batch", json={"requests": [{"model": NAME, "version": "production",
                                                                     **body}]}).json()["results"][0]
            assert batch["version"] == "1" and batch["mean"] == first[0]["mean"]

        # overwrite one object of version 1 in the bucket: both replicas refuse version 1, version 2 serves
        key = sorted(k for k in fs.find(f"{BUCKET}/plant-a/{NAME}/1") if k.endswith(".npy"))[0]
        raw = bytearray(fs.cat(key))
        raw[-3] ^= 0xFF
        fs.pipe(key, bytes(raw))
        t_bad = time.monotonic()
        for rep in replicas:
            _wait(lambda rep=rep: rep.get("/health/ready").json()["refused"], timeout=30)
        timings["refusal_pickup"] = time.monotonic() - t_bad
        for rep in replicas:
            ready = rep.get("/health/ready").json()
            assert ready["models"] == {NAME: ["2"]}
            assert [r["path"] for r in ready["refused"]] == [f"{NAME}/1"]
            assert "checksum" in ready["refused"][0]["reason"] and Path(key).name in ready["refused"][0]["reason"]
            r = rep.post(f"/v1/models/{NAME}/versions/1/predict", body)
            assert r.status_code == 404 and r.json()["field"] == "version" and "checksum" in r.json()["detail"]
            assert URL not in r.json()["detail"] and f"{NAME}/1/" in r.json()["detail"]
            r = rep.post(f"/v1/models/{NAME}/versions/production/predict", body)
            assert r.status_code == 404 and "names version 1" in r.json()["detail"]
            assert _answer(rep.post(f"/v1/models/{NAME}/predict", body)) == second[0]
            assert _metric(rep.get("/metrics").text, "gpnarx_bundles_refused") == 1.0
    finally:
        for rep in replicas:
            rep.close()
    timings["total"] = time.monotonic() - t_start
    print("registry-remote timings [s]: " + ", ".join(f"{k}={v:.2f}" for k, v in timings.items()))


# ------------------------------------------------------------------------------------------ memory://
@pytest.fixture
def mem(tmp_path, monkeypatch):
    import fsspec

    monkeypatch.setenv("GPNARX_CACHE", str(tmp_path / "cache"))
    url = f"memory://reg-{tmp_path.name}"
    yield url, fsspec.filesystem("memory")
    fsspec.filesystem("memory").rm(f"/reg-{tmp_path.name}", recursive=True)


def test_publish_writes_the_manifest_last_and_unpublished_versions_are_skipped(mem, monkeypatch):
    from gpnarx.storage import remote as storage

    url, fs = mem
    model = _tiny_model(1)
    order = []
    real = storage.RemoteStore.put_file

    def spy(self, src, rel):
        order.append(rel.rsplit("/", 1)[-1])
        if fail["now"] and len(order) == 3:  # the third object of the version
            raise storage.StorageError("injected failure")
        return real(self, src, rel)

    fail = {"now": True}
    monkeypatch.setattr(storage.RemoteStore, "put_file", spy)
    with pytest.raises(storage.StorageError, match="injected"):
        save_bundle(model, url, "m", fs=FS, units={"u": "N", "y": "m"})
    assert Registry(url).scan().names() == []  # the failed write left nothing listed
    fail["now"] = False
    order.clear()
    path = save_bundle(model, url, "m", fs=FS, units={"u": "N", "y": "m"})
    assert path.name == "1" and order[-2:] == ["manifest.sha256", "manifest.json"]
    # a write in progress elsewhere (objects, no manifest) is neither listed nor refused, and its
    # version number is not reused
    fs.pipe(f"/{url.split('://')[1]}/m/2/theta.npy", b"x")
    reg = Registry(url).scan()
    assert reg.versions("m") == ["1"] and reg.refused == []
    assert save_bundle(model, url, "m", fs=FS, units={"u": "N", "y": "m"}).name == "3"
    with pytest.raises(BundleError, match="never overwritten"):
        save_bundle(model, url, "m", "3", fs=FS, units={"u": "N", "y": "m"})


def test_lazy_registry_builds_on_first_use_keeps_at_most_max_loaded_and_reuses_unchanged(mem):
    url, fs = mem
    models = [_tiny_model(s) for s in (1, 2, 3)]
    for m in models:
        save_bundle(m, url, "m", fs=FS, units={"u": "N", "y": "m"})
    reg = Registry(url, lazy=True, max_loaded=2).scan()
    assert reg.versions("m") == ["1", "2", "3"] and reg.loaded_count() == 0
    u = np.sin(np.linspace(0, 20, 200)) * 10
    for v, m in zip(("1", "2", "3"), models):
        b = reg.get("m", v)
        assert np.array_equal(b.model.simulate(u, n_paths=8, seed=0).mean, m.simulate(u, n_paths=8, seed=0).mean)
    assert reg.loaded_count() == 2 and not reg.is_built("m", "1") and reg.is_built("m", "3")
    assert reg.get("m", "3") is reg.get("m", "latest")
    # a rescan with nothing changed keeps the built models and does not copy anything again
    cache = Path(os.environ["GPNARX_CACHE"])
    stamps = {p: p.stat().st_mtime_ns for p in cache.rglob("*.npy")}
    again = reg.rescan()
    assert again.get("m", "3") is reg.get("m", "3")
    assert {p: p.stat().st_mtime_ns for p in cache.rglob("*.npy")} == stamps
    # a damaged cached copy is copied again from the store, not refused
    victim = next(p for p in cache.rglob("theta.npy") if p.parent.parent.name == "2")  # NAME/VERSION/KEY/
    victim.write_bytes(b"damaged")
    fresh = Registry(url, lazy=True).scan()
    assert fresh.refused == [] and fresh.versions("m") == ["1", "2", "3"]


def test_aliases_and_model_refs(mem, tmp_path):
    url, fs = mem
    save_bundle(_tiny_model(1), url, "m", fs=FS, units={"u": "N", "y": "m"})
    save_bundle(_tiny_model(2), url, "m", fs=FS, units={"u": "N", "y": "m"})
    assert parse_model_ref("m:production") == ("m", "production") and parse_model_ref("m:2") == ("m", "2")
    for bad in ("m:0", "m:1a", "m:pro duction", "m:" + "a" * 40):
        with pytest.raises(BundleError, match="version"):
            parse_model_ref(bad)
    with pytest.raises(BundleError, match="implicit"):
        write_aliases(url, "m", {"latest": "1"})
    write_aliases(url, "m", {"production": "1", "canary": "9"})
    reg = Registry(url, lazy=True).scan()
    assert reg.aliases_of("m") == {"latest": "2", "production": "1"}  # canary names no served version
    assert reg.resolve("m", "production") == "1" and reg.resolve("m") == "2"
    with pytest.raises(KeyError, match="names version 9"):
        reg.get("m", "canary")
    with pytest.raises(KeyError, match="alias 'staging'"):
        reg.get("m", "staging")
    # a malformed aliases file is listed as refused; the versions keep serving
    fs.pipe(f"/{url.split('://')[1]}/m/aliases.json", b"{not json")
    reg = reg.rescan()
    assert reg.versions("m") == ["1", "2"] and [r["path"] for r in reg.refused] == [f"{url}/m/aliases.json"]
    # the same on a local folder, written by a temporary file and a rename
    local = tmp_path / "local"
    save_bundle(_tiny_model(1), local, "m", fs=FS, units={"u": "N", "y": "m"})
    write_aliases(f"file://{local}", "m", {"production": "1"})
    assert json.loads((local / "m" / "aliases.json").read_text())["aliases"] == {"production": "1"}
    assert Registry(local).scan().get("m", "production").version == "1"
    assert not [p for p in (local / "m").iterdir() if p.name.startswith(".")]


def test_cli_on_a_registry_url(mem, tmp_path, capsys):
    from gpnarx.cli.main import main

    url, fs = mem
    model = _tiny_model(1)
    save_bundle(model, url, "m", fs=FS, units={"u": "N", "y": "m"})
    save_bundle(_tiny_model(2), url, "m", fs=FS, units={"u": "N", "y": "m"})
    u = np.sin(np.linspace(0, 20, 120)) * 10
    rec = tmp_path / "rec.npz"
    np.savez(rec, u=u, fs=FS)
    assert main(["alias", "set", "--registry", url, "m", "production", "1", "--json"]) == 0
    capsys.readouterr()
    assert main(["predict", "--registry", url, "--model", "m:production", str(rec), "--mc", "8", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["version"] == "1" and np.allclose(d["mean"], model.simulate(u, n_paths=8, seed=0).mean)
    assert main(["alias", "list", "--registry", url, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["aliases"] == {"m": {"latest": "2", "production": "1"}}
    # errors are one line naming what is wrong
    for argv, needle, code in ((["alias", "set", "--registry", url, "m", "latest", "1"], "implicit", 2),
                               (["alias", "set", "--registry", url, "m", "prod", "7"], "version '7'", 1),
                               (["predict", "--registry", url, "--model", "m:staging", str(rec)], "alias 'staging'", 1),
                               (["serve", "--registry", "nosuchproto://x/y"], "nosuchproto", 1)):
        assert main(argv) == code, argv
        err = capsys.readouterr().err
        assert needle in err and err.count("\n") == 1, err


def test_unreadable_store_starts_unready_then_keeps_the_last_good_registry(mem, monkeypatch):
    from fastapi.testclient import TestClient

    from gpnarx.service.app import create_app
    from gpnarx.service.settings import Settings
    from gpnarx.storage import remote as storage

    url, fs = mem
    save_bundle(_tiny_model(1), url, "m", fs=FS, units={"u": "N", "y": "m"})
    real, down = storage.RemoteStore.listing, {"on": True}

    def listing(self, under=""):
        if down["on"]:
            raise storage.StorageError(f"{self.uri(under)}: listing failed (ConnectTimeoutError)")
        return real(self, under)

    monkeypatch.setattr(storage.RemoteStore, "listing", listing)
    c = TestClient(create_app(url, Settings(workers=1, queue_size=1, registry_poll=0)), raise_server_exceptions=False)
    r = c.get("/health/ready")
    assert r.status_code == 503 and "could not be read" in r.json()["detail"] and "ConnectTimeout" in r.json()["detail"]
    assert c.get("/health/live").status_code == 200
    down["on"] = False
    assert c.post("/v1/admin/reload").json()["added"] == ["m:1"]
    assert c.get("/health/ready").status_code == 200
    down["on"] = True
    r = c.post("/v1/admin/reload")
    assert r.status_code == 503 and "keep serving" in r.json()["detail"]
    body = {"u": (np.sin(np.linspace(0, 20, 64)) * 10).tolist(), "fs": FS, "mc_paths": 8}
    assert c.post("/v1/models/m/predict", json=body).json()["version"] == "1"
    assert c.get("/health/ready").status_code == 200


def test_a_file_changed_after_the_scan_is_refused_when_first_built(tmp_path):
    from fastapi.testclient import TestClient

    from gpnarx.service.app import create_app
    from gpnarx.service.settings import Settings

    for seed in (1, 2):
        save_bundle(_tiny_model(seed), tmp_path, "m", fs=FS, units={"u": "N", "y": "m"})
    c = TestClient(create_app(tmp_path, Settings(workers=1, queue_size=1, registry_poll=0)),
                   raise_server_exceptions=False)
    assert c.get("/health/ready").json()["models"] == {"m": ["1", "2"]}  # verified, none built yet
    npy = tmp_path / "m" / "2" / "theta.npy"
    raw = bytearray(npy.read_bytes())
    raw[-2] ^= 0xFF
    npy.write_bytes(bytes(raw))
    body = {"u": (np.sin(np.linspace(0, 20, 64)) * 10).tolist(), "fs": FS, "mc_paths": 8}
    r = c.post("/v1/models/m/versions/2/predict", json=body)
    assert r.status_code == 404 and "m/2/theta.npy: sha256 checksum" in r.json()["detail"]
    assert str(tmp_path) not in r.json()["detail"]
    ready = c.get("/health/ready").json()
    assert ready["models"] == {"m": ["1"]} and [x["path"] for x in ready["refused"]] == ["m/2"]
    assert c.post("/v1/models/m/predict", json=body).json()["version"] == "1"


def test_readers_sharing_one_cache_folder_never_refuse_each_others_copies(s3, tmp_path, monkeypatch):
    import threading

    fs, _env = s3
    url = f"s3://{BUCKET}/shared-cache"
    monkeypatch.setenv("GPNARX_CACHE", str(tmp_path / "one-cache"))
    for seed in (1, 2, 3):
        save_bundle(_tiny_model(seed), url, "m", fs=FS, units={"u": "N", "y": "m"})
    results, errors = [], []

    def read():
        try:
            reg = Registry(url, lazy=True).scan()
            results.append((reg.versions("m"), reg.refused, reg.get("m", "2").version))
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    for _round in range(3):
        threads = [threading.Thread(target=read) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        # the store changes: every reader copies version 1 again, into the one shared folder
        fs.pipe(f"{BUCKET}/shared-cache/m/1/notes.txt", f"round {_round}".encode())
    assert not errors, errors
    assert len(results) == 12 and all(r == (["1", "2", "3"], [], "2") for r in results), results
    copies = [p for p in (tmp_path / "one-cache").rglob("manifest.json")]
    assert len(copies) == 3 + 2  # one copy per version and listing (version 1 was listed three ways)
