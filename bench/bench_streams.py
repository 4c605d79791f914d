"""Streams per replica: how many sensor streams one `gpnarx serve` replica follows in real time.

    python bench/bench_streams.py --registry DIR --model NAME --record PATH [--operation predict|novelty]
                                  [--seconds S] [--streams 4,8,12,16] [--workers 2] [--method linear]
    python bench/bench_streams.py --quick      # a small Bouc-Wen bundle trained here, short records

Starts ``gpnarx serve`` on a free loopback port. Each stream is a client that sends a record (its u, and y for
novelty) in chunks of ``--chunk`` seconds at the pace the plant produces them: chunk k leaves at t0 + k x chunk
(each stream's t0 offset by an even share of one chunk, as independent sensors are), carrying the previous
answer's ``state`` token (``return_state``), so a late answer delays the next chunk. A stream is followed in real
time when every chunk is answered within its chunk time; a replica sustains N streams when, with N streams at
once, the 99th-percentile latency is below the chunk time, nothing is shed (503) or fails, and no stream falls
behind its schedule.

For each N of ``--streams`` (ascending; it stops after the first N that is not sustained) the run prints the
latency percentiles, 503s, errors and the largest lag behind schedule. Baseline, same run: one stream alone, its
median chunk latency t1; a replica with W workers could at most follow floor(W x chunk / t1) such streams if
chunks shared the workers perfectly. RESULT line: ``streams=`` (the largest N sustained), ``baseline=`` (that
bound), ``ratio=``, ``p99_ms_at_max=`` (``none`` when no count was sustained), ``p99_ms_past_max=`` (the first count
not sustained), ``limit=`` (``found``, or a lower bound when every count tried was
sustained), the load average before and after (``load_before``, ``load_after``).

``--replicas R`` (default 1): R ``gpnarx serve`` processes behind one address, as docs/deploy.md runs them (Compose's
service name, a Kubernetes Service): a round-robin TCP proxy in this process hands each new client connection to
the next replica, every replica with the same ``GPNARX_STREAM_KEY``, so a stream's chunks may land on any replica
and continue there from the state token. The bound is then R x W x chunk / t1 and ``replicas=`` is on the line.
All replicas, the proxy and the clients share this machine's cores.

Units: seconds of signal per chunk [s], latencies [ms].
"""
from __future__ import annotations

import argparse
import asyncio
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def chunks_of(u, y, fs: float, chunk_s: float, seconds: float | None):
    """[(u_k, y_k)] of ``chunk_s`` seconds each over the first ``seconds`` of the record (all of it when None)."""
    n = int(round(chunk_s * fs))
    total = u.size if seconds is None else min(u.size, int(round(seconds * fs)))
    return [(u[i:i + n], None if y is None else y[i:i + n]) for i in range(0, total - n + 1, n)]


async def stream(client, path: str, parts, fs: float, chunk_s: float, t0: float, operation: str, method: str):
    """One stream: each chunk at its schedule (or at once when the previous answer came late); its latencies [s],
    status codes and the largest lag behind schedule [s]."""
    state, lat, codes, lag = None, [], [], 0.0
    for k, (u, y) in enumerate(parts):
        due = t0 + k * chunk_s
        now = time.perf_counter()
        if now < due:
            await asyncio.sleep(due - now)
        lag = max(lag, time.perf_counter() - due)
        body = {"u": u.tolist(), "fs": fs, "method": method, "return_state": True}
        if operation == "novelty":
            body["y"] = y.tolist()
            if k == 0:
                body["start"] = "rest"
        if state is not None:
            body["state"] = state
            body.pop("start", None)
        t = time.perf_counter()
        r = await client.post(path, json=body)
        lat.append(time.perf_counter() - t)
        codes.append(r.status_code)
        if r.status_code != 200:
            break
        state = r.json().get("state")
    return lat, codes, lag


async def run_streams(url: str, path: str, parts, fs: float, chunk_s: float, n: int, operation: str, method: str):
    import httpx

    limits = httpx.Limits(max_connections=n + 4, max_keepalive_connections=n + 4)
    async with httpx.AsyncClient(base_url=url, timeout=120.0, limits=limits) as client:
        start = time.perf_counter() + 0.5
        jobs = [stream(client, path, parts, fs, chunk_s, start + i * chunk_s / n, operation, method) for i in range(n)]
        return await asyncio.gather(*jobs)


def summarise(results, chunk_s: float) -> dict:
    lat = np.concatenate([np.asarray(r[0]) for r in results]) * 1e3
    codes = [c for r in results for c in r[1]]
    lag = max(r[2] for r in results)
    p99 = float(np.percentile(lat, 99)) if lat.size else math.inf
    out = {"chunks": int(lat.size), "p50_ms": float(np.percentile(lat, 50)) if lat.size else math.inf,
           "p99_ms": p99, "max_ms": float(lat.max()) if lat.size else math.inf,
           "shed_503": codes.count(503), "errors": sum(1 for c in codes if c not in (200, 503)),
           "max_lag_s": float(lag)}
    out["sustained"] = bool(p99 < chunk_s * 1e3 and out["shed_503"] == 0 and out["errors"] == 0
                            and lag < chunk_s)
    return out


class RoundRobinProxy:
    """One loopback address in front of several: each accepted connection is piped, both ways, to the next
    backend port in turn (per connection, as a Kubernetes Service or Compose's DNS name spreads clients). Runs
    its own event loop on a daemon thread; ``connections`` counts the connections handed to each backend."""

    def __init__(self, backends: list[int]):
        import threading

        self.backends, self.port = list(backends), C.free_port()
        self.connections = [0] * len(self.backends)
        self._next = 0
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True, name="bench-streams-proxy")
        self._thread.start()
        if not self._ready.wait(10.0):
            raise SystemExit("the round-robin proxy did not start")

    async def _pipe(self, reader, writer):
        try:
            while data := await reader.read(65536):
                writer.write(data)
                await writer.drain()
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            writer.close()

    async def _handle(self, reader, writer):
        k = self._next
        self._next = (k + 1) % len(self.backends)
        self.connections[k] += 1
        try:
            br, bw = await asyncio.open_connection("127.0.0.1", self.backends[k])
        except OSError:
            writer.close()
            return
        await asyncio.gather(self._pipe(reader, bw), self._pipe(br, writer))

    def _serve(self):
        asyncio.set_event_loop(self._loop)
        server = self._loop.run_until_complete(asyncio.start_server(self._handle, "127.0.0.1", self.port))
        self._ready.set()
        try:
            self._loop.run_forever()
        finally:
            server.close()

    def close(self):
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(5.0)


def quick_registry(tmp: Path) -> tuple[str, Path]:
    """A small Bouc-Wen bundle (bench_load's) and a 12 s multisine record of it, for --quick."""
    import bench_load as L

    name = L.train_bundle(tmp, quick=True)
    u = L._multisine(int(12 * L.FS), 7)
    rec = tmp / "record.npz"
    np.savez(rec, u=u, y=L._noisy(L._simulate(u), 8), fs=np.float64(L.FS))
    return name, rec


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a small bundle trained here, 4 s of each stream")
    ap.add_argument("--registry", default=None)
    ap.add_argument("--model", default=None)
    ap.add_argument("--record", default=None, help="a record file or LMS folder (u [and y]) to stream")
    ap.add_argument("--operation", choices=("predict", "novelty"), default="predict")
    ap.add_argument("--method", default="linear", help="free-run method of every chunk (default linear)")
    ap.add_argument("--chunk", type=float, default=1.0, help="seconds of signal per chunk (default 1)")
    ap.add_argument("--seconds", type=float, default=None, help="seconds of each stream (default: the record)")
    ap.add_argument("--streams", default=None, help="stream counts to try, ascending (default 4,8,12,16,20,24)")
    ap.add_argument("--workers", type=int, default=2, help="server worker threads (default 2)")
    ap.add_argument("--replicas", type=int, default=1,
                    help="gpnarx serve processes behind one round-robin address (default 1)")
    args = ap.parse_args(argv)
    from gpnarx.storage.record_files import read_record

    tmp = tempfile.TemporaryDirectory(prefix="gpnarx-bench-streams-")
    if args.quick:
        model, record = quick_registry(Path(tmp.name))
        registry, seconds, counts = Path(tmp.name), args.seconds or 4.0, args.streams or "2,4"
    else:
        if not (args.registry and args.model and args.record):
            raise SystemExit("give --registry, --model and --record (or --quick)")
        registry, model, record = Path(args.registry), args.model, args.record
        seconds, counts = args.seconds, args.streams or "4,8,12,16,20,24"
    counts = sorted({int(c) for c in str(counts).split(",")})
    rec = read_record(record)
    if args.operation == "novelty" and rec.y is None:
        raise SystemExit("--operation novelty needs a record with y")
    parts = chunks_of(rec.u, rec.y, rec.fs, args.chunk, seconds)
    if len(parts) < 2:
        raise SystemExit(f"the record gives {len(parts)} chunk(s) of {args.chunk} s; need at least 2")
    if args.replicas < 1:
        raise SystemExit("--replicas must be at least 1")
    path = f"/v1/models/{model}/{args.operation}"
    ports = [C.free_port() for _ in range(args.replicas)]
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("GPNARX_API_KEY", None)
    if args.replicas > 1:  # one key on every replica: a stream's token is good on any of them
        env["GPNARX_STREAM_KEY"] = os.urandom(16).hex()
    load_before = C.load()
    procs, logs, proxy = [], [], None
    try:
        for k, port in enumerate(ports):
            log_path = Path(tmp.name) / f"serve-{k}.log"
            logs.append((open(log_path, "w"), log_path))
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "gpnarx", "serve", "--registry", str(registry), "--port", str(port),
                 "--workers", str(args.workers), "--queue", str(4 * max(counts)), "--log-level", "warning"],
                cwd=str(ROOT), env=env, stdout=logs[-1][0], stderr=logs[-1][0]))
        for proc, port, (_, log_path) in zip(procs, ports, logs):
            C.wait_ready(f"http://127.0.0.1:{port}", proc, 300.0, log_path)
        if args.replicas > 1:
            proxy = RoundRobinProxy(ports)
            url = f"http://127.0.0.1:{proxy.port}"
        else:
            url = f"http://127.0.0.1:{ports[0]}"
        one = summarise(asyncio.run(run_streams(url, path, parts, rec.fs, args.chunk, 1, args.operation,
                                                args.method)), args.chunk)
        slots = args.replicas * args.workers
        bound = int(slots * args.chunk * 1e3 // one["p50_ms"]) if one["p50_ms"] > 0 else 0
        print(f"one stream: p50 {one['p50_ms']:.1f} ms, p99 {one['p99_ms']:.1f} ms over {one['chunks']} chunks "
              f"-> at most {bound} streams on {args.replicas} x {args.workers} workers", file=sys.stderr)
        best, at_best, rows = 0, None, []
        for n in counts:
            s = summarise(asyncio.run(run_streams(url, path, parts, rec.fs, args.chunk, n, args.operation,
                                                  args.method)), args.chunk)
            rows.append((n, s))
            print(f"{n:3d} streams: p50 {s['p50_ms']:.0f} ms, p99 {s['p99_ms']:.0f} ms, max {s['max_ms']:.0f} ms, "
                  f"503 {s['shed_503']}, errors {s['errors']}, lag {s['max_lag_s']:.2f} s -> "
                  f"{'sustained' if s['sustained'] else 'NOT sustained'}", file=sys.stderr)
            if not s["sustained"]:
                break
            best, at_best = n, s
    finally:
        if proxy is not None:
            proxy.close()
        for proc in procs:
            C.stop_server(proc)
        for f, _ in logs:
            f.close()
    extra = {"replicas": args.replicas, "connections": "/".join(map(str, proxy.connections))} if proxy else {}
    C.result(bench="streams", model=model, operation=args.operation, method=args.method, chunk_s=args.chunk,
             stream_s=len(parts) * args.chunk, workers=args.workers, **extra, streams=best, baseline=bound,
             baseline_what=("replicas-x-" if args.replicas > 1 else "") + "workers-x-chunk/one-stream-p50",
             ratio=round(best / bound, 3) if bound else None, single_p50_ms=round(one["p50_ms"], 1),
             p99_ms_at_max=round(at_best["p99_ms"], 1) if at_best else "none",
             p99_ms_past_max=round(rows[-1][1]["p99_ms"], 1) if rows and not rows[-1][1]["sustained"] else "none",
             tried=",".join(str(n) for n, _ in rows),
             limit="lower-bound" if rows and rows[-1][1]["sustained"] else "found",
             load_before=round(load_before, 2), load_after=round(C.load(), 2))
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
