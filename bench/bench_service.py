"""HTTP overhead of the prediction service against the same prediction called in-process.

    python bench/bench_service.py [--registry DIR --model NAME] [--samples 2048] [--paths 256]
                                  [--repeats 10] [--clients 8] [--rps-requests 16]

Starts ``gpnarx serve`` in a subprocess on a free loopback port (without ``--registry`` it first
trains a small Bouc-Wen bundle, ny = nu = 10, 600 training points, into a temporary registry),
then, interleaving the two so both see the same machine load:

- in-process: ``bundle.model.simulate(u, n_paths, seed)`` plus the metrics of the answer
  (fit, RMSE, coverage), in this process, with the service's process tuning (BLAS limited to one
  thread, glibc mmap threshold raised; see ``service.settings``);
- over HTTP: ``POST /v1/models/NAME/predict`` with the same record, measured end to end by an
  httpx client (serialisation of u and y, parsing, validation, queueing, the prediction, JSON
  rendering of mean/lower/upper/std, transfer, client-side parsing).

Then requests/s with ``--clients`` concurrent clients. Also reports the JSON rendering time of
the answer with the service's renderer (orjson when installed) and with the standard library.

Baseline (equal work; no scikit-learn equivalent): the same prediction in-process, same model,
record, paths, seed and process tuning, alternating with the HTTP call (A, B, A, B, ...).
Prints one line: ``RESULT http_p50_ms=... http_p95_ms=... inproc_ms=... baseline=<inproc_ms>
ratio=<median of per-repetition http / in-process times> overhead_pct=... rps=...`` (+ context keys).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import _common as C  # noqa: E402  (bench/ is on sys.path when run as a script)

FS = 750.0


def train_bundle(registry: Path) -> str:
    from gpnarx.model.estimator import GPNARX
    from gpnarx.storage.bundle import save_bundle
    from gpnarx.training import excitations as ex
    from gpnarx.training.simulators.boucwen import BoucWen

    bw = BoucWen()
    rng = np.random.default_rng(0)
    recs = []
    for amp in (10.0, 50.0):
        u = ex.swept_sine(FS, amp, 5.0, 150.0, rate=53.0)
        y = bw.simulate(u)["y"]
        recs.append((u, y + 0.05 * np.std(y) * rng.normal(size=y.size)))
    u = ex.multisine(FS, 10.0, 5.0, 150.0, 2048, seed=1)
    y = bw.simulate(u)["y"]
    recs.append((u, y + 0.05 * np.std(y) * rng.normal(size=y.size)))
    model = GPNARX(ny=10, nu=10, max_train_points=600, n_restarts=0).fit(recs)
    save_bundle(model, registry, "bench-boucwen", "1", fs=FS, units={"u": "N", "y": "m"},
                physics={"mass": 2.0, "input_gain": 1.0, "output": "displacement"}, training={})
    return "bench-boucwen"


def pct(a, q):
    return float(np.percentile(np.asarray(a), q))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--registry", default=None)
    ap.add_argument("--model", default=None, help="model name (default: the only/first one with fs 750 Hz)")
    ap.add_argument("--samples", type=int, default=2048)
    ap.add_argument("--paths", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--clients", type=int, default=8)
    ap.add_argument("--rps-requests", type=int, default=16)
    ap.add_argument("--workers", type=int, default=None, help="server worker threads (default: the service's)")
    args = ap.parse_args(argv)

    import httpx

    from gpnarx.model.metrics import summary
    from gpnarx.service.app import limit_blas_threads, render_json, tune_malloc
    from gpnarx.service.settings import Settings
    from gpnarx.storage.registry import Registry

    # the in-process baseline runs under the same process tuning as the service (service.settings)
    limit_blas_threads(Settings().blas_threads)
    tune_malloc(Settings().mmap_threshold)
    tmp = None
    if args.registry:
        registry = Path(args.registry)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="gpnarx-bench-")
        registry = Path(tmp.name)
        t0 = time.perf_counter()
        train_bundle(registry)
        print(f"[bench] trained a bundle in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    reg = Registry(registry).scan()
    name = args.model or next((n for n in reg.names() if reg.get(n).fs == FS), None) or reg.names()[0]
    bundle = reg.get(name)
    fs = bundle.fs

    from gpnarx.training import excitations as ex

    u = ex.multisine(fs, 10.0, 5.0, min(150.0, 0.4 * fs), args.samples, seed=7)
    run0 = bundle.model.simulate(u, n_paths=8, seed=1)
    y = run0.mean + 0.01 * np.std(run0.mean) * np.random.default_rng(3).normal(size=u.size)
    body = {"u": u.tolist(), "y": y.tolist(), "fs": fs, "mc_paths": args.paths, "seed": 0}
    payload = json.dumps(body).encode()

    port = C.free_port()
    url = f"http://127.0.0.1:{port}"
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [sys.executable, "-m", "gpnarx", "serve", "--registry", str(registry), "--port", str(port),
           "--log-level", "warning"]
    if args.workers:
        cmd += ["--workers", str(args.workers)]
    proc = subprocess.Popen(cmd, cwd=str(ROOT), env=env, stderr=subprocess.DEVNULL)
    try:
        C.wait_ready(url, proc, 600.0)
        headers = {"content-type": "application/json"}
        with httpx.Client(base_url=url, timeout=600) as c:
            path = f"/v1/models/{name}/predict"
            c.post(path, content=payload, headers=headers).raise_for_status()  # warm-up
            inproc, http, server_compute = [], [], []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                run = bundle.model.simulate(u, n_paths=args.paths, seed=0)
                summary(y, run.mean, run.lower, run.upper)
                inproc.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                r = c.post(path, content=payload, headers=headers)
                d = r.json()
                http.append(time.perf_counter() - t0)
                timing = dict(part.strip().split(";dur=") for part in r.headers.get("server-timing", "").split(",")
                              if ";dur=" in part)
                if "compute" in timing:
                    server_compute.append(float(timing["compute"]) / 1e3)
                assert r.status_code == 200 and len(d["mean"]) == args.samples, r.text[:200]
            same = np.array_equal(np.asarray(d["mean"]), run.mean)

        # JSON rendering of the answer: the service's renderer vs the standard library
        answer = {"mean": run.mean, "lower": run.lower, "upper": run.upper, "std": run.std}
        t0 = time.perf_counter()
        for _ in range(20):
            render_json(answer)
        render_ms = (time.perf_counter() - t0) / 20 * 1e3
        t0 = time.perf_counter()
        for _ in range(20):
            json.dumps({k: v.tolist() for k, v in answer.items()}).encode()
        stdlib_ms = (time.perf_counter() - t0) / 20 * 1e3

        # throughput with concurrent clients
        counts = [args.rps_requests // args.clients + (1 if i < args.rps_requests % args.clients else 0)
                  for i in range(args.clients)]
        errors = []

        def client(n):
            with httpx.Client(base_url=url, timeout=600) as cc:
                for _ in range(n):
                    rr = cc.post(path, content=payload, headers=headers)
                    if rr.status_code != 200:
                        errors.append(rr.status_code)

        threads = [threading.Thread(target=client, args=(n,)) for n in counts]
        t0 = time.perf_counter()
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wall = time.perf_counter() - t0
        rps = sum(counts) / wall
    finally:
        C.stop_server(proc)
        if tmp is not None:
            tmp.cleanup()

    in_ms = pct(inproc, 50) * 1e3
    http50, http95 = pct(http, 50) * 1e3, pct(http, 95) * 1e3
    ratio = C.median_ratio(http, inproc)
    overhead = (http50 - in_ms) / in_ms * 100.0
    n_train = bundle.model.posterior_.points.shape[0]
    print(f"RESULT http_p50_ms={http50:.1f} http_p95_ms={http95:.1f} inproc_ms={in_ms:.1f} baseline={in_ms:.1f} "
          f"baseline_what=inprocess-simulate-same-model-same-tuning ratio={ratio:.3f} overhead_pct={overhead:.1f} "
          f"rps={rps:.2f} clients={args.clients} "
          f"rps_requests={sum(counts)} rps_errors={len(errors)} samples={args.samples} paths={args.paths} "
          f"repeats={args.repeats} model={name} n_train={n_train} inproc_p95_ms={pct(inproc, 95) * 1e3:.1f} "
          f"server_compute_p50_ms={pct(server_compute, 50) * 1e3 if server_compute else float('nan'):.1f} "
          f"render_ms={render_ms:.2f} stdlib_json_ms={stdlib_ms:.2f} identical_to_inproc={int(same)} "
          f"cpus={os.cpu_count()}")


if __name__ == "__main__":
    main()
