"""The seven fault probes of issue 33, on loopback, against real ``gpnarx serve`` processes.

    python tools/fault_probes.py [--registry DIR] [--only 1,2,...] [--out FILE]

Without ``--registry`` the shipped ``bouc-wen`` model is built first (``gpnarx train bouc-wen``) into
a temporary registry. Each probe starts its own server(s) on free 127.0.0.1 ports and prints one
line ``RESULT probe=<n> ... before=<the issue's figure>`` (``before_*`` fields quote the issue's
report, measured on the code before the fixes; they are not re-measured here). The load average of
the machine is printed with every probe: the latency figures (probe 4 above all) depend on it.

1. Emptied store: a registry on S3 (``moto_server`` on loopback), two replicas polling every second
   (``GPNARX_REGISTRY_POLL=1``); the bucket is emptied for 20 s, then restored. Counted: predicts
   that did not answer 200, and /health/ready answers that were not 200.
2. Unauthenticated flood: ``GPNARX_API_KEY`` set; 16 raw connections post 30 MiB of invalid JSON at
   once without the key. The server's RSS before and its peak (VmHWM) and the answers.
3. Shutdown: a predict sized to take about 33 s is cut by SIGTERM 5 s after it starts, once with
   the default drain window (it should finish: 200) and once with ``GPNARX_DRAIN_TIMEOUT=5`` (a 503
   problem with Retry-After at the end of the window).
4. Overload: 32 clients (24 posting predicts of 2048 samples x 64 Monte Carlo paths, 8 posting
   batches of two 16384-sample linearised records, about 700 kB of JSON) for 20 s against the
   default workers and queue; ``/health/live`` polled every 100 ms on its own connection from its
   own process (p50, max), with the same poll on the idle server just before (``idle_*``).
5. Host header: ``GET /v1/models/`` with ``Host: evil.example``: the status and any Location.
6. Slow clients: 200 connections each sending one header line every 5 s (never finishing the
   head): how many the server closed, and when (``GPNARX_HEADER_TIMEOUT``, default 10 s).
7. Leftovers: a publish SIGKILLed in the middle, to a local registry (a ``.tmp-*`` folder) and to
   the S3 registry (objects without a manifest); the leftovers before and after a server's start
   (local) or scans (S3, ``GPNARX_REGISTRY_LEFTOVER_AGE=5``, polled every second; the time from the
   kill to their removal includes the server's start-up).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

from gpnarx.client.raw import raw_post

MODEL = "bouc-wen"
FS = 750.0
BEFORE = {  # the report, measured before the fixes
    1: "227_predicts_404_over_28s_and_ready_503",
    2: "400_and_RSS_212MB_to_1.5GB",
    3: "500_text/plain_at_32s_no_Retry-After",
    4: "live_p50_0.94s_max_1.8s;503_p50_2.1s_max_122s;Retry-After_always_2",
    5: "307_to_http://evil.example/v1/models",
    6: "0_of_200_closed_in_60s",
    7: "1_.tmp-*_folder_left_until_a_write_an_hour_later",
}


def load() -> str:
    return "/".join(f"{x:.2f}" for x in os.getloadavg())


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def result(probe: int, **kv) -> None:
    fields = " ".join(f"{k}={v}" for k, v in kv.items())
    print(f"RESULT probe={probe} {fields} load={load()} before={BEFORE[probe]}", flush=True)


def record(n: int, seed: int = 0) -> list:
    """A multisine force record of ``n`` samples at 750 Hz [N] (5-150 Hz, 10 N rms)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / FS
    f = np.linspace(5, 150, 40)
    u = np.sin(2 * np.pi * f[:, None] * t + rng.uniform(0, 2 * np.pi, (40, 1))).sum(0)
    return (u * 10.0 / u.std()).round(6).tolist()


class Server:
    """``gpnarx serve`` in a subprocess on a free port; ``env`` is added to this environment."""

    def __init__(self, registry, env: dict | None = None, log: Path | None = None):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        full = {**os.environ, "OPENBLAS_NUM_THREADS": "1", **(env or {})}
        self.log = open(log or os.devnull, "w")
        self.proc = subprocess.Popen([sys.executable, "-m", "gpnarx", "serve", "--registry", str(registry), "--port",
                                      str(self.port), "--log-level", "warning"], env=full, stdout=self.log,
                                     stderr=subprocess.STDOUT)
        t0 = time.monotonic()
        while time.monotonic() - t0 < 120:
            if self.proc.poll() is not None:
                raise RuntimeError(f"gpnarx serve exited {self.proc.returncode}")
            try:
                if httpx.get(self.url + "/health/ready", timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        raise RuntimeError("gpnarx serve did not become ready in 120 s")

    def rss_mb(self, key: str = "VmRSS") -> float:
        with open(f"/proc/{self.proc.pid}/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) / 1024
        return float("nan")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()


# ------------------------------------------------------------------------------------------ S3 on loopback
class Moto:
    """``moto_server`` on a free port, a bucket, and the environment a client of it needs."""

    def __init__(self, bucket: str = "plant"):
        self.port = free_port()
        self.proc = subprocess.Popen(["moto_server", "-H", "127.0.0.1", "-p", str(self.port)],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.env = {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing",
                    "AWS_DEFAULT_REGION": "us-east-1", "AWS_ENDPOINT_URL": f"http://127.0.0.1:{self.port}"}
        os.environ.update(self.env)
        import s3fs

        t0 = time.monotonic()
        while True:
            try:
                httpx.get(self.env["AWS_ENDPOINT_URL"], timeout=1)
                break
            except httpx.HTTPError:
                if time.monotonic() - t0 > 30:
                    raise
                time.sleep(0.2)
        s3fs.S3FileSystem.clear_instance_cache()
        self.fs = s3fs.S3FileSystem()
        self.bucket = bucket
        self.fs.mkdir(bucket)

    def upload(self, local_registry: Path, prefix: str) -> str:
        """Every bundle of ``local_registry`` under ``s3://bucket/prefix``, each manifest last."""
        files = sorted(p for p in local_registry.rglob("*") if p.is_file() and not any(
            part.startswith(".") for part in p.relative_to(local_registry).parts))
        last = [p for p in files if p.name in ("manifest.sha256", "manifest.json")]
        for p in [p for p in files if p not in last] + sorted(last, key=lambda p: p.name != "manifest.sha256"):
            self.fs.put_file(str(p), f"{self.bucket}/{prefix}/{p.relative_to(local_registry).as_posix()}")
        return f"s3://{self.bucket}/{prefix}"

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(10)


# ------------------------------------------------------------------------------------------ probes
def probe_empty_store(moto: Moto, registry: Path, work: Path) -> None:
    url = moto.upload(registry, "p1")
    replicas = [Server(url, {"GPNARX_REGISTRY_POLL": "1", "GPNARX_CACHE": str(work / f"cache-{i}")},
                       work / f"p1-replica{i}.log") for i in range(2)]
    body = {"u": record(512), "fs": FS, "method": "linear"}
    stats = {"normal": [], "empty": [], "restored": []}
    ready_bad = [0]
    phase = ["normal"]
    stop = threading.Event()

    def traffic(i):
        with httpx.Client(base_url=replicas[i].url, timeout=60) as c:
            while not stop.is_set():
                try:
                    stats[phase[0]].append(c.post(f"/v1/models/{MODEL}/predict", json=body).status_code)
                    ready = c.get("/health/ready").status_code
                except httpx.HTTPError:
                    stats[phase[0]].append(0)
                    ready = 0
                ready_bad[0] += ready != 200
                time.sleep(0.05)

    threads = [threading.Thread(target=traffic, args=(i,)) for i in range(2)]
    try:
        for t in threads:
            t.start()
        time.sleep(5)
        phase[0] = "empty"
        moto.fs.rm(f"{moto.bucket}/p1", recursive=True)  # the store comes back with an empty bucket
        time.sleep(20)
        moto.upload(registry, "p1")
        phase[0] = "restored"
        time.sleep(5)
        stop.set()
        for t in threads:
            t.join()
        held = [httpx.get(r.url + "/health/ready").json().get("registry_held") for r in replicas]
    finally:
        stop.set()
        for r in replicas:
            r.stop()
    failed = {k: sum(s != 200 for s in v) for k, v in stats.items()}
    result(1, failed_while_empty=f"{failed['empty']}/{len(stats['empty'])}",
           failed_all=f"{sum(failed.values())}/{sum(len(v) for v in stats.values())}", empty_s=20,
           ready_not_200=ready_bad[0], held_after_restore=sum(h is not None for h in held))


def probe_flood(registry: Path, work: Path) -> None:
    srv = Server(registry, {"GPNARX_API_KEY": "s3cret"}, work / "p2.log")
    try:
        junk = b"[" * (30 * 1024 * 1024)
        base = srv.rss_mb()
        statuses, t0 = [], time.perf_counter()
        threads = [threading.Thread(target=lambda: statuses.append(
            raw_post(srv.port, f"/v1/models/{MODEL}/predict", junk))) for _ in range(16)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        took = time.perf_counter() - t0
        peak, after = srv.rss_mb("VmHWM"), srv.rss_mb()
    finally:
        srv.stop()
    codes = ",".join(f"{c}x{statuses.count(c)}" for c in sorted(set(statuses)))
    result(2, statuses=codes, rss_before_mb=f"{base:.0f}", rss_peak_mb=f"{peak:.0f}", rss_after_mb=f"{after:.0f}",
           all_answered_s=f"{took:.2f}")


def probe_shutdown(registry: Path, work: Path, target_s: float = 33.0) -> None:
    env = {"GPNARX_MAX_MC_WORK": str(2**30), "GPNARX_MAX_SAMPLES": str(2**20)}
    srv = Server(registry, env, work / "p3-size.log")
    try:  # size the request: path-steps per second of one predict on this machine now
        n, paths = 2048, 64
        t0 = time.perf_counter()
        r = httpx.post(srv.url + f"/v1/models/{MODEL}/predict", timeout=300,
                       json={"u": record(n), "fs": FS, "method": "mc", "mc_paths": paths, "seed": 0})
        r.raise_for_status()
        rate = n * paths / (time.perf_counter() - t0)
    finally:
        srv.stop()
    samples = int(min(2**20, max(4096, rate * target_s / paths)))
    body = {"u": record(samples), "fs": FS, "method": "mc", "mc_paths": paths, "seed": 0}
    out = {}
    for label, extra in (("default_drain", {}), ("drain_5s", {"GPNARX_DRAIN_TIMEOUT": "5"})):
        srv = Server(registry, {**env, **extra}, work / f"p3-{label}.log")
        got: dict = {}

        def call(srv=srv, got=got):
            t0 = time.perf_counter()
            try:
                r = httpx.post(srv.url + f"/v1/models/{MODEL}/predict", json=body, timeout=300)
                got.update(status=r.status_code, ctype=r.headers.get("content-type", "").split(";")[0],
                           retry_after=r.headers.get("retry-after"))
            except httpx.HTTPError as exc:
                got.update(status=f"no-answer({type(exc).__name__})", ctype="-", retry_after=None)
            got["s"] = time.perf_counter() - t0

        t = threading.Thread(target=call)
        t.start()
        time.sleep(5)
        srv.proc.send_signal(signal.SIGTERM)
        t.join()
        srv.proc.wait(300)
        srv.log.close()
        out[label] = got
    d, c = out["default_drain"], out["drain_5s"]
    result(3, request_samples=samples, mc_paths=paths, sized_s=f"{samples * paths / rate:.0f}",
           default_drain_status=d["status"], default_drain_answer_s=f"{d['s']:.1f}",
           drain5_status=c["status"], drain5_type=c["ctype"], drain5_retry_after=c["retry_after"],
           drain5_answer_s=f"{c['s']:.1f}")


_POLL = r"""
import json, sys, time
import httpx
url, seconds = sys.argv[1], float(sys.argv[2])
out, end = [], time.monotonic() + seconds
with httpx.Client(base_url=url, timeout=30) as c:
    while time.monotonic() < end:
        t0 = time.perf_counter()
        c.get("/health/live")
        out.append(time.perf_counter() - t0)
        time.sleep(0.1)
print(json.dumps(out))
"""


def _poll_live(url: str, seconds: float) -> subprocess.Popen:
    """``/health/live`` every 100 ms for ``seconds`` on its own connection, from its own process (so the
    clients' threads in this process never delay its clock); ``.communicate()[0]`` holds the latencies."""
    return subprocess.Popen([sys.executable, "-c", _POLL, url, str(seconds)], stdout=subprocess.PIPE, text=True)


def _latencies(p: subprocess.Popen) -> list:
    return json.loads(p.communicate()[0])


def probe_overload(registry: Path, work: Path, seconds: float = 20.0) -> None:
    srv = Server(registry, None, work / "p4.log")
    # bodies encoded once: the clients spend no CPU of the shared machine re-encoding them
    single = json.dumps({"u": record(2048, 1), "fs": FS, "method": "mc", "mc_paths": 64, "seed": 0}).encode()
    batch = json.dumps({"requests": [{"model": MODEL, "u": record(16384, k), "fs": FS, "method": "linear"}
                                     for k in (2, 3)]}).encode()
    try:
        idle = _latencies(_poll_live(srv.url, 3))
        answers, stop = [], threading.Event()

        def client(i):
            path, body = ("/v1/batch", batch) if i % 4 == 3 else (f"/v1/models/{MODEL}/predict", single)
            with httpx.Client(base_url=srv.url, timeout=300, headers={"content-type": "application/json"}) as c:
                while not stop.is_set():
                    t0 = time.perf_counter()
                    try:
                        r = c.post(path, content=body)
                    except httpx.HTTPError:  # the server closed the connection before answering
                        answers.append(("conn", time.perf_counter() - t0, None))
                        continue
                    answers.append((r.status_code, time.perf_counter() - t0, r.headers.get("retry-after")))

        clients = [threading.Thread(target=client, args=(i,)) for i in range(32)]
        for t in clients:
            t.start()
        live = _latencies(_poll_live(srv.url, seconds))
        stop.set()
        for t in clients:
            t.join()
    finally:
        srv.stop()
    shed = [a for a in answers if a[0] == 503]
    other = sum(1 for a in answers if a[0] != "conn" and a[0] >= 500 and a[0] != 503)
    ra = sorted({a[2] for a in shed if a[2] is not None}, key=lambda v: int(v))
    result(4, clients=32, live_p50_s=f"{statistics.median(live):.3f}", live_max_s=f"{max(live):.3f}",
           live_n=len(live), idle_live_p50_s=f"{statistics.median(idle):.3f}", idle_live_max_s=f"{max(idle):.3f}",
           ok_200=sum(a[0] == 200 for a in answers), shed_503=len(shed), other_5xx=other,
           no_answer=sum(a[0] == "conn" for a in answers),
           shed_p50_s=f"{statistics.median([a[1] for a in shed]):.3f}" if shed else "-",
           shed_max_s=f"{max(a[1] for a in shed):.3f}" if shed else "-",
           retry_after_values=",".join(ra) or "-")


def probe_host(registry: Path, work: Path) -> None:
    srv = Server(registry, None, work / "p5.log")
    try:
        r = httpx.get(srv.url + "/v1/models/", headers={"Host": "evil.example"}, follow_redirects=False)
    finally:
        srv.stop()
    result(5, status=r.status_code, location=r.headers.get("location", "none"),
           type=r.headers.get("content-type", "").split(";")[0])


def probe_slow(registry: Path, work: Path, n: int = 200, watch: float = 40.0) -> None:
    srv = Server(registry, None, work / "p6.log")
    socks, closed, first = [], {}, {}
    try:
        t0 = time.monotonic()
        for _ in range(n):
            s = socket.create_connection(("127.0.0.1", srv.port))
            s.setblocking(False)
            s.sendall(f"POST /v1/models/{MODEL}/predict HTTP/1.1\r\nHost: x\r\n".encode())
            socks.append(s)
        last_send = time.monotonic()
        while time.monotonic() - t0 < watch and len(closed) < n:
            for i, s in enumerate(socks):
                if i in closed:
                    continue
                try:
                    data = s.recv(4096)
                except BlockingIOError:
                    continue
                except OSError:
                    data = b""
                if data:
                    first.setdefault(i, data[:12].decode("latin-1"))
                    continue
                closed[i] = time.monotonic() - t0
            if time.monotonic() - last_send >= 5:
                for i, s in enumerate(socks):
                    if i not in closed:
                        try:
                            s.send(b"X-Slow: 1\r\n")
                        except OSError:
                            pass
                last_send = time.monotonic()
            time.sleep(0.05)
    finally:
        for s in socks:
            s.close()
        srv.stop()
    codes = sorted({v.split()[1] for v in first.values() if len(v.split()) > 1})
    result(6, connections=n, closed=len(closed), closed_max_s=f"{max(closed.values()):.1f}" if closed else "-",
           answered=",".join(codes) or "-", watched_s=f"{watch:g}")


_KILLED = r"""
import sys, time
from pathlib import Path
from gpnarx.storage import bundle
from gpnarx.storage.remote import RemoteStore

target, name = sys.argv[1], sys.argv[2]
b = bundle.load_bundle(Path(sys.argv[3]))
if target.startswith("s3://"):
    real = RemoteStore.put_file
    def put_file(self, src, rel):
        real(self, src, rel)
        print(rel, flush=True)
        time.sleep(600)  # killed here: after the first object, before the manifest
    RemoteStore.put_file = put_file
    bundle.save_bundle(b.model, target, name, fs=b.fs, units=b.manifest["units"])
else:
    def fill(tmp, version):
        (tmp / "theta.npy").write_bytes(b"partial")
        print(tmp, flush=True)
        time.sleep(600)  # killed here: inside the publish, before the rename
    bundle._write_new_version(Path(target), name, None, fill)
"""


def _killed_publish(target: str, source_bundle: Path) -> str:
    p = subprocess.Popen([sys.executable, "-c", _KILLED, target, MODEL, str(source_bundle)], stdout=subprocess.PIPE,
                         text=True)
    line = p.stdout.readline().strip()
    p.send_signal(signal.SIGKILL)
    p.wait()
    return line


def probe_leftovers(moto: Moto, registry: Path, work: Path) -> None:
    local = work / "p7-registry"
    shutil.copytree(registry, local)
    source = max((registry / MODEL).iterdir(), key=lambda p: int(p.name) if p.name.isdigit() else -1)
    _killed_publish(str(local), source)
    before_local = len(list((local / MODEL).glob(".tmp-*")))
    srv = Server(local, None, work / "p7-local.log")
    after_local = len(list((local / MODEL).glob(".tmp-*")))
    srv.stop()
    url = moto.upload(registry, "p7")
    rel = _killed_publish(url, source)
    killed = time.monotonic()
    version = rel.split("/")[-2] if rel.count("/") >= 2 else "?"

    def unpublished() -> int:
        keys = moto.fs.find(f"{moto.bucket}/p7/{MODEL}")
        groups = {}
        for k in keys:
            parts = k.split("/")[3:]
            if len(parts) >= 2 and parts[0].isdigit():
                groups.setdefault(parts[0], set()).add(parts[-1])
        return sum(1 for files in groups.values() if "manifest.json" not in files)

    before_s3 = unpublished()
    srv = Server(url, {"GPNARX_REGISTRY_POLL": "1", "GPNARX_REGISTRY_LEFTOVER_AGE": "5",
                       "GPNARX_CACHE": str(work / "p7-cache")}, work / "p7-s3.log")
    try:
        while unpublished() and time.monotonic() - killed < 90:
            time.sleep(0.5)
        gone_s = time.monotonic() - killed
        after_s3 = unpublished()
        models = httpx.get(srv.url + "/v1/models").json()
    finally:
        srv.stop()
    listed = [m.get("versions") for m in models.get("models", [])] if isinstance(models, dict) else models
    result(7, local_tmp_before=before_local, local_tmp_after_start=after_local, s3_unpublished_before=before_s3,
           s3_unpublished_after=after_s3, s3_removed_after_kill_s=f"{gone_s:.1f}", s3_leftover_age_s=5,
           s3_killed_version=version, listed=json.dumps(listed, separators=(",", ":")))


def build_registry(dest: Path) -> Path:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "gpnarx", "train", MODEL, "--registry", str(dest)], check=True,
                   stdout=subprocess.DEVNULL, env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    print(f"# built {MODEL} into {dest} in {time.perf_counter() - t0:.0f} s", flush=True)
    return dest


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--registry", type=Path, default=None, help=f"a registry holding {MODEL} (default: built now)")
    ap.add_argument("--only", default="1,2,3,4,5,6,7", help="comma-separated probe numbers")
    args = ap.parse_args()
    only = {int(x) for x in args.only.split(",")}
    work = Path(tempfile.mkdtemp(prefix="gpnarx-faults-"))
    print(f"# fault probes (issue 33) on {os.cpu_count()} CPUs, load {load()}; work folder {work}", flush=True)
    registry = args.registry or build_registry(work / "registry")
    moto = Moto() if only & {1, 7} else None
    try:
        for k, probe in ((1, lambda: probe_empty_store(moto, registry, work)), (2, lambda: probe_flood(registry, work)),
                         (3, lambda: probe_shutdown(registry, work)), (4, lambda: probe_overload(registry, work)),
                         (5, lambda: probe_host(registry, work)), (6, lambda: probe_slow(registry, work)),
                         (7, lambda: probe_leftovers(moto, registry, work))):
            if k in only:
                t0 = time.perf_counter()
                probe()
                print(f"# probe {k} took {time.perf_counter() - t0:.0f} s", flush=True)
    finally:
        if moto is not None:
            moto.stop()
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
