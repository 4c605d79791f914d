"""Bounded loopback load test of the HTTP service: concurrent mixed calls, then an overload.

    python bench/bench_load.py [--quick] [--clients 16] [--requests 128] [--samples 256] [--paths 32]
                               [--workers 2] [--queue Q] [--overload N] [--registry DIR --model NAME]

Starts ``gpnarx serve`` in a subprocess on a free 127.0.0.1 port (without ``--registry`` it first
trains a small Bouc-Wen GP-NARX, ny = nu = 8, 300 training points (150 with --quick), with a
novelty calibration, into a temporary registry). A fixed list of ``--requests`` calls mixes, in a
repeating cycle of four, predict, novelty, predict and a batch of three records (predict, novelty,
predict): multisine records of ``--samples`` samples at 750 Hz, ``--paths`` Monte Carlo paths.

1. Baseline, same run: one client sends the whole list sequentially (latency per call type, req/s).
2. Load: ``--clients`` concurrent clients (httpx async, one connection each) share the same list;
   every answer must be 200 (errors are counted and printed; the script exits 1 if any). The
   server's queue is ``--queue`` (default: clients, so the load phase is never shed).
   Phases 1 and 2 alternate ``--reps`` times (A, B, A, B; same calls, same server and process
   tuning); ``ratio=`` is the median over repetitions of concurrent / sequential throughput.
3. Overload: ``--overload`` requests (default 3 x (workers + queue)), each a 4x longer predict,
   sent at once: more than the server's workers + queue slots, so the surplus must be shed with
   503 + Retry-After at once and no other 5xx may appear. Meanwhile, and before the load
   (idle), ``/health/live`` is polled every 20 ms on its own connection: its p95 latency is
   printed for both.

Prints tables and one line ``RESULT rps=<load req/s> baseline=<sequential req/s> ratio=<rps/baseline>
errors=... p50_<type>_ms=... p95_<type>_ms=... shed_503=... retry_after_ok=... other_5xx=...
health_p95_idle_ms=... health_p95_overload_ms=... ...`` (bench/_common.result format).
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

import _common as C

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

FS = 750.0
NAME = "load-boucwen"
TYPES = ("predict", "novelty", "batch")


# ------------------------------------------------------------------------------------------ set-up
def _simulate(u):
    from gpnarx.training.simulators.boucwen import BoucWen

    return BoucWen().simulate(np.asarray(u, float))["y"]


def _multisine(n, seed, rms=10.0):
    from gpnarx.training import excitations as ex

    return ex.multisine(FS, rms, 5.0, 150.0, n, seed=seed)


def _noisy(y, seed, level=0.05):
    return y + level * np.std(y) * np.random.default_rng(seed).normal(size=y.size)


def train_bundle(registry: Path, quick: bool) -> str:
    """A small Bouc-Wen GP-NARX with a novelty calibration (3 healthy records, 1 % false alarms)."""
    from gpnarx.model.estimator import GPNARX
    from gpnarx.model.novelty import calibrate_threshold, novelty_score
    from gpnarx.storage.bundle import save_bundle

    n_rec = 768 if quick else 1024
    recs = []
    for k, s in enumerate((1, 2)):
        u = _multisine(n_rec, s)
        recs.append((u, _noisy(_simulate(u), 100 + k)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GPNARX(ny=8, nu=8, max_train_points=150 if quick else 300, n_restarts=0).fit(recs)
        scores = []
        for s in (11, 12, 13):
            u = _multisine(256, s)
            run = model.simulate(u, n_paths=32, seed=0)
            scores.append(novelty_score(_noisy(_simulate(u), 300 + s), run.mean, run.std)["score"])
    save_bundle(model, registry, NAME, "1", fs=FS, units={"u": "N", "y": "m"},
                physics={"mass": 2.0, "input_gain": 1.0, "output": "displacement"},
                novelty=calibrate_threshold(scores, 0.01), training={"note": "bench_load"})
    return NAME


def make_calls(model: str, n_calls: int, samples: int, paths: int) -> list[tuple[str, str, bytes]]:
    """The fixed mix: (type, path, JSON body) for each call, a cycle of predict, novelty, predict, batch."""
    calls = []
    for i in range(n_calls):
        u = _multisine(samples, 1000 + i)
        y = _simulate(u)
        rec = {"u": u.tolist(), "fs": FS, "mc_paths": paths, "seed": i}
        kind = ("predict", "novelty", "predict", "batch")[i % 4]
        if kind == "predict":
            body, path = {**rec, "y": y.tolist()}, f"/v1/models/{model}/predict"
        elif kind == "novelty":
            body, path = {**rec, "y": _noisy(y, i).tolist()}, f"/v1/models/{model}/novelty"
        else:
            items = []
            for j, op in enumerate(("predict", "novelty", "predict")):
                uj = _multisine(samples, 5000 + 3 * i + j)
                item = {"model": model, "operation": op, "u": uj.tolist(), "fs": FS, "mc_paths": paths, "seed": j}
                if op == "novelty":
                    item["y"] = _noisy(_simulate(uj), j).tolist()
                items.append(item)
            body, path = {"requests": items}, "/v1/batch"
        calls.append((kind, path, json.dumps(body).encode()))
    return calls


def pct(a, q) -> float:
    return float(np.percentile(np.asarray(a, float), q)) if len(a) else float("nan")


# ------------------------------------------------------------------------------------------ phases
HEADERS = {"content-type": "application/json"}


def _check(kind: str, r) -> str | None:
    """None when the answer is a complete success, else a short description of the error."""
    if r.status_code != 200:
        return f"{kind}: HTTP {r.status_code} {r.text[:120]}"
    d = r.json()
    if kind == "batch":
        bad = [x for x in d.get("results", []) if "status" in x]
        if len(d.get("results", [])) != 3 or bad:
            return f"batch: {bad[:1] or 'wrong number of results'}"
    elif kind == "predict" and "mean" not in d:
        return "predict: no mean"
    elif kind == "novelty" and "score" not in d:
        return "novelty: no score"
    return None


def _server_timing(header: str) -> dict:
    out = {}
    for part in header.split(","):
        if ";dur=" in part:
            k, v = part.strip().split(";dur=", 1)
            out[k] = float(v) / 1e3
    return out


async def run_calls(url: str, calls, clients: int):
    """``clients`` workers share the list (closed loop); returns (latencies by type, errors, wall s)."""
    import httpx

    lat = {k: [] for k in TYPES}
    lat["server"] = []  # (queue s, compute s) from the Server-Timing header of predict/novelty answers
    errors: list[str] = []
    queue: asyncio.Queue = asyncio.Queue()
    for c in calls:
        queue.put_nowait(c)

    async def client(c):
        async with c:
            while True:
                try:
                    kind, path, body = queue.get_nowait()
                except asyncio.QueueEmpty:
                    return
                t0 = time.perf_counter()
                try:
                    r = await c.post(path, content=body, headers=HEADERS)
                    err = _check(kind, r)
                    timing = _server_timing(r.headers.get("server-timing", ""))
                    if {"queue", "compute"} <= set(timing):
                        lat["server"].append((timing["queue"], timing["compute"]))
                except httpx.HTTPError as exc:
                    err = f"{kind}: {type(exc).__name__} {exc}"
                lat[kind].append(time.perf_counter() - t0)
                if err:
                    errors.append(err)

    # clients are made before the clock starts (each builds an SSL context: CPU time in this process)
    pool = [httpx.AsyncClient(base_url=url, timeout=300, limits=httpx.Limits(max_connections=1))
            for _ in range(clients)]
    t0 = time.perf_counter()
    await asyncio.gather(*(client(c) for c in pool))
    return lat, errors, time.perf_counter() - t0


async def poll_health(url: str, stop: asyncio.Event, out: list, period=0.02, max_polls=None):
    import httpx

    async with httpx.AsyncClient(base_url=url, timeout=30, limits=httpx.Limits(max_connections=1)) as c:
        await c.get("/health/live")  # open the connection
        n = 0
        while not stop.is_set() and (max_polls is None or n < max_polls):
            t0 = time.perf_counter()
            r = await c.get("/health/live")
            out.append((time.perf_counter() - t0, r.status_code))
            n += 1
            await asyncio.sleep(period)


async def overload(url: str, path: str, body: bytes, n: int):
    """``n`` requests at once (one connection each) while /health/live is polled; returns answers."""
    import httpx

    health: list = []
    stop = asyncio.Event()
    poller = asyncio.ensure_future(poll_health(url, stop, health))
    await asyncio.sleep(0.1)
    results = []

    async def one(c):
        t0 = time.perf_counter()
        try:
            r = await c.post(path, content=body, headers=HEADERS)
            results.append((r.status_code, r.headers.get("retry-after"), time.perf_counter() - t0,
                            r.headers.get("content-type", "")))
        except httpx.HTTPError as exc:
            results.append((f"{type(exc).__name__}", None, time.perf_counter() - t0, ""))

    # one client, a connection per request (no pooling limit), made before the clock starts
    limits = httpx.Limits(max_connections=None, max_keepalive_connections=None)
    async with httpx.AsyncClient(base_url=url, timeout=300, limits=limits) as c:
        t0 = time.perf_counter()
        await asyncio.gather(*(one(c) for _ in range(n)))
        wall = time.perf_counter() - t0
    stop.set()
    await poller
    return results, health, wall


# ------------------------------------------------------------------------------------------ main
def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (whole script well under a minute)")
    ap.add_argument("--threads", type=int, default=1, help="BLAS threads of this process (training the bundle)")
    ap.add_argument("--registry", default=None)
    ap.add_argument("--model", default=None)
    ap.add_argument("--clients", type=int, default=None, help="concurrent clients (default 16; 8 with --quick)")
    ap.add_argument("--requests", type=int, default=None, help="calls in the mix (default 128; 32 with --quick)")
    ap.add_argument("--samples", type=int, default=None, help="samples per record (default 256; 128 with --quick)")
    ap.add_argument("--paths", type=int, default=None, help="Monte Carlo paths (default 32; 16 with --quick)")
    ap.add_argument("--workers", type=int, default=2, help="server worker threads (default 2)")
    ap.add_argument("--queue", type=int, default=None, help="server queue size (default: --clients)")
    ap.add_argument("--reps", type=int, default=2, help="interleaved repetitions of the sequential and concurrent "
                    "phases (default 2)")
    ap.add_argument("--overload", type=int, default=None, help="simultaneous requests of the overload phase "
                    "(default 3 x (workers + queue))")
    args = ap.parse_args(argv)
    clients = args.clients or (8 if args.quick else 16)
    n_calls = args.requests or (32 if args.quick else 128)
    samples = args.samples or (128 if args.quick else 256)
    paths = args.paths or (16 if args.quick else 32)
    queue_size = clients if args.queue is None else args.queue
    reps = max(1, args.reps)
    n_over = args.overload or 3 * (args.workers + queue_size)
    if not 1 <= clients <= 256 or n_calls < 4 or n_over <= args.workers + queue_size:
        raise SystemExit("need 1 <= clients <= 256, requests >= 4 and overload > workers + queue")

    import httpx
    from threadpoolctl import threadpool_limits

    from _common import fmt, result

    threadpool_limits(limits=args.threads, user_api="blas")
    tmp = None
    t_setup = time.perf_counter()
    if args.registry:
        registry = Path(args.registry)
        model = args.model
        if model is None:
            from gpnarx.storage.registry import Registry

            reg = Registry(registry).scan()
            model = next((n for n in reg.names() if reg.get(n).fs == FS), None)
            if model is None:
                raise SystemExit(f"no model with fs {FS} Hz in {registry}")
    else:
        tmp = tempfile.TemporaryDirectory(prefix="gpnarx-bench-load-")
        registry = Path(tmp.name)
        model = train_bundle(registry, args.quick)
    calls = make_calls(model, n_calls, samples, paths)
    u_long = _multisine(4 * samples, 99)
    long_body = json.dumps({"u": u_long.tolist(), "fs": FS, "mc_paths": paths, "seed": 0}).encode()
    print(f"[bench] set-up (bundle, {n_calls} calls) {time.perf_counter() - t_setup:.1f} s", file=sys.stderr)

    port = C.free_port()
    url = f"http://127.0.0.1:{port}"
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("GPNARX_API_KEY", None)
    log_file = tempfile.NamedTemporaryFile(prefix="gpnarx-bench-load-", suffix=".log", delete=False)  # noqa: SIM115
    log_path = Path(log_file.name)
    cmd = [sys.executable, "-m", "gpnarx", "serve", "--registry", str(registry), "--port", str(port),
           "--workers", str(args.workers), "--queue", str(queue_size), "--log-level", "warning"]
    proc = subprocess.Popen(cmd, cwd=str(ROOT), env=env, stdout=log_file, stderr=log_file)
    try:
        C.wait_ready(url, proc, 180.0, log_path)
        # warm-up: one call of each type
        with httpx.Client(base_url=url, timeout=300) as c:
            for kind in TYPES:
                k, path, body = next(x for x in calls if x[0] == kind)
                err = _check(k, c.post(path, content=body, headers=HEADERS))
                if err:
                    raise SystemExit(f"warm-up failed: {err}")

        idle_health: list = []
        asyncio.run(poll_health(url, asyncio.Event(), idle_health, max_polls=50))
        # sequential (baseline) and concurrent phases alternate, A, B, A, B, ...: the same calls on the same
        # server, so a change of machine load hits both; ratio = median of the per-repetition throughput ratios
        base_lat, load_lat = {k: [] for k in (*TYPES, "server")}, {k: [] for k in (*TYPES, "server")}
        base_err, load_err, base_walls, load_walls = [], [], [], []
        for _ in range(reps):
            for lat, err, walls, n_clients in ((base_lat, base_err, base_walls, 1),
                                               (load_lat, load_err, load_walls, clients)):
                lt, er, wall = asyncio.run(run_calls(url, calls, n_clients))
                for k, v in lt.items():
                    lat[k].extend(v)
                err.extend(er)
                walls.append(wall)
        over, over_health, over_wall = asyncio.run(overload(url, f"/v1/models/{model}/predict", long_body, n_over))
        with httpx.Client(base_url=url, timeout=30) as c:
            metrics = c.get("/metrics").text
    finally:
        C.stop_server(proc)
        log_file.close()
        server_log = log_path.read_text()
        log_path.unlink(missing_ok=True)
        if tmp is not None:
            tmp.cleanup()

    base_rps = n_calls / C.median(base_walls)
    rps = n_calls / C.median(load_walls)
    ratio = C.median_ratio(base_walls, load_walls)  # (n / load wall) / (n / sequential wall), per repetition
    statuses = [s for s, *_ in over]
    n200 = sum(1 for s in statuses if s == 200)
    n503 = sum(1 for s in statuses if s == 503)
    retry_ok = sum(1 for s, ra, _, ct in over if s == 503 and ra and ra.isdigit() and int(ra) > 0
                   and ct.startswith("application/problem+json"))
    other_5xx = sum(1 for s in statuses if not isinstance(s, int) or (s >= 500 and s != 503))
    other = sum(1 for s in statuses if isinstance(s, int) and s not in (200, 503) and s < 500)
    shed_lat = [t for s, _, t, _ in over if s == 503]
    h_idle = [t for t, s in idle_health if s == 200]
    h_over = [t for t, s in over_health if s == 200]
    h_bad = sum(1 for _, s in idle_health + over_health if s != 200)

    print(f"\nserver: {args.workers} workers, queue {queue_size}; model {model}; {samples} samples, {paths} paths; "
          f"mix of {n_calls} calls (predict/novelty/batch of 3 = "
          f"{sum(1 for c in calls if c[0] == 'predict')}/{sum(1 for c in calls if c[0] == 'novelty')}/"
          f"{sum(1 for c in calls if c[0] == 'batch')}); load avg {os.getloadavg()[0]:.1f}, {os.cpu_count()} CPUs")
    print(f"{'phase':<22}{'type':<9}{'n':>5}{'p50 ms':>10}{'p95 ms':>10}")
    for phase, lat in (("sequential (1 client)", base_lat), (f"load ({clients} clients)", load_lat)):
        for k in TYPES:
            print(f"{phase:<22}{k:<9}{len(lat[k]):>5}{pct(lat[k], 50) * 1e3:>10.1f}{pct(lat[k], 95) * 1e3:>10.1f}")
    for phase, lat in (("sequential", base_lat), ("load", load_lat)):
        q = [a for a, _ in lat["server"]]
        comp = [b for _, b in lat["server"]]
        print(f"server side ({phase}, predict/novelty): queue p50 {pct(q, 50) * 1e3:.1f} ms, compute p50 "
              f"{pct(comp, 50) * 1e3:.1f} ms")
    print(f"throughput ({reps} interleaved repetitions, median): sequential {base_rps:.2f} req/s, {clients} clients "
          f"{rps:.2f} req/s (ratio {ratio:.2f}); "
          f"errors {len(base_err)} sequential, {len(load_err)} under load")
    for e in (base_err + load_err)[:5]:
        print("  error:", e)
    print(f"overload: {n_over} simultaneous predicts of {4 * samples} samples (capacity {args.workers + queue_size}): "
          f"{n200} x 200, {n503} x 503 (Retry-After + problem: {retry_ok}), other 4xx {other}, other 5xx/transport "
          f"{other_5xx}; 503 answered in p95 {pct(shed_lat, 95) * 1e3:.1f} ms; phase {over_wall:.1f} s")
    print(f"/health/live p95: idle {pct(h_idle, 95) * 1e3:.2f} ms ({len(h_idle)} polls), overload "
          f"{pct(h_over, 95) * 1e3:.2f} ms ({len(h_over)} polls, max {max(h_over, default=float('nan')) * 1e3:.1f} ms)")
    shed_metric = next((ln.split()[-1] for ln in metrics.splitlines() if ln.startswith("gpnarx_requests_shed_total")),
                       "nan")
    kv = {"rps": rps, "baseline": base_rps, "baseline_what": "sequential-client-same-calls-same-server",
          "ratio": ratio, "errors": len(load_err) + len(base_err), "clients": clients, "requests": n_calls,
          "reps": reps}
    for k in TYPES:
        kv[f"p50_{k}_ms"] = pct(load_lat[k], 50) * 1e3
        kv[f"p95_{k}_ms"] = pct(load_lat[k], 95) * 1e3
        kv[f"seq_p50_{k}_ms"] = pct(base_lat[k], 50) * 1e3
    kv["compute_p50_ms"] = pct([b for _, b in load_lat["server"]], 50) * 1e3
    kv["seq_compute_p50_ms"] = pct([b for _, b in base_lat["server"]], 50) * 1e3
    kv["queue_p50_ms"] = pct([a for a, _ in load_lat["server"]], 50) * 1e3
    kv.update(overload=n_over, capacity=args.workers + queue_size, ok_200=n200, shed_503=n503,
              retry_after_ok=retry_ok, other_5xx=other_5xx, other_4xx=other, shed_p95_ms=pct(shed_lat, 95) * 1e3,
              health_p95_idle_ms=pct(h_idle, 95) * 1e3, health_p95_overload_ms=pct(h_over, 95) * 1e3,
              health_ratio=pct(h_over, 95) / pct(h_idle, 95) if h_idle and h_over else float("nan"),
              health_errors=h_bad, server_shed_total=fmt(float(shed_metric)) if shed_metric != "nan" else "nan",
              workers=args.workers, queue=queue_size, samples=samples, paths=paths)
    result(**kv)
    if "Traceback" in server_log:
        print("server log holds a traceback:\n" + server_log[-3000:], file=sys.stderr)
    failed = len(load_err) + len(base_err) > 0 or other_5xx > 0 or n503 == 0 or retry_ok != n503 or h_bad > 0
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
