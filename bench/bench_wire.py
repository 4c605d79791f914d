"""Size and time of one 64 s predict answer on the wire: JSON, gzip JSON and NPZ.

    python bench/bench_wire.py [--seconds 64] [--fs 1024] [--repeats 5] [--quick]

Trains a small linear single-degree-of-freedom GP-NARX (ny = nu = 2) at fs = 1024 Hz into a temporary
registry, serves it with uvicorn on a free loopback port (in this process, one worker thread), and
asks ``POST /v1/models/m/predict`` for a ``--seconds`` record (64 s: 65,536 samples) three ways,
interleaved (A, B, C, A, B, C, ...) so machine load hits all of them:

- ``json``: JSON body, JSON answer, no compression (the service's only format before);
- ``gzip``: JSON body, JSON answer with ``Accept-Encoding: gzip``;
- ``npz``: NPZ body (``application/x-npz``), NPZ answer (``Accept: application/x-npz``).

Each is timed end to end by an httpx client, from encoding the request to holding ``mean``, ``lower``,
``upper`` and ``std`` as numpy arrays; ``compute`` (the prediction itself, from ``Server-Timing``) is
subtracted to give ``wire`` time (encoding, transfer, parsing, validation, rendering). The prediction
uses the linearised band (``method=linear``), the same on all three, so the wire is what differs.
Answer sizes are the bytes on the wire (``Content-Length``).

The published run is stored in ``docs/runs/bench/wire.txt``; ``--render PAGE`` re-renders the table of PAGE
(docs/api.md, "Wire formats") from it with the results pages' renderer (``gpnarx.training.pages.wire``;
tests/test_wire_formats.py checks that the page is that render).

Baseline: the JSON body and answer. Prints one line ``RESULT json_bytes=... gzip_bytes=... npz_bytes=...
json_ms=... gzip_ms=... npz_ms=... json_wire_ms=... baseline=<json_wire_ms> ratio=<median of the per-repetition
JSON / NPZ wire times> ...``.
"""
from __future__ import annotations

import argparse
import io
import socket
import statistics
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def sdof(u: np.ndarray, fs: float) -> np.ndarray:
    """Linear oscillator (20 Hz, 2 % damping, 1 kg), zero-order hold: displacement [m] for force u [N]."""
    from scipy import signal

    wn = 2 * np.pi * 20.0
    sys_c = signal.StateSpace([[0.0, 1.0], [-wn**2, -2 * 0.02 * wn]], [[0.0], [1.0]], [[1.0, 0.0]], [[0.0]])
    d = sys_c.to_discrete(1.0 / fs)
    _, y, _ = signal.dlsim((d.A, d.B, d.C, d.D, d.dt), u)
    return np.asarray(y).ravel()


def build_registry(root: Path, fs: float) -> None:
    from gpnarx.model.estimator import GPNARX
    from gpnarx.storage.bundle import save_bundle

    rng = np.random.default_rng(0)
    u = rng.standard_normal(2048)
    y = sdof(u, fs)
    y = y + 0.01 * np.std(y) * rng.standard_normal(y.size)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GPNARX(ny=2, nu=2, max_train_points=300, n_restarts=0).fit([(u, y)])
    save_bundle(model, root, "m", "1", fs=fs, units={"u": "N", "y": "m"})


class Server:
    """uvicorn on 127.0.0.1 (free port) in a background thread."""

    def __init__(self, app):
        import uvicorn

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.bind(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}"
        self.server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on"))
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)

    def __enter__(self):
        self.thread.start()
        t0 = time.monotonic()
        while not self.server.started:
            if time.monotonic() - t0 > 30:
                raise RuntimeError("uvicorn did not start")
            time.sleep(0.02)
        return self

    def __exit__(self, *exc):
        self.server.should_exit = True
        self.thread.join(timeout=30)
        self.sock.close()


def compute_ms(resp) -> float:
    for part in resp.headers.get("server-timing", "").split(","):
        name, _, dur = part.strip().partition(";dur=")
        if name == "compute":
            return float(dur)
    return float("nan")


def call(client, kind: str, u: np.ndarray, fs: float):
    """(seconds, answer bytes on the wire, compute ms, mean) of one predict call of the given kind."""
    t0 = time.perf_counter()
    if kind == "npz":
        buf = io.BytesIO()
        np.savez(buf, u=u, fs=np.float64(fs))
        r = client.post("/v1/models/m/predict", params={"method": "linear"}, content=buf.getvalue(),
                        headers={"content-type": "application/x-npz", "accept": "application/x-npz",
                                 "accept-encoding": "identity"})
        r.raise_for_status()
        with np.load(io.BytesIO(r.content), allow_pickle=False) as z:
            arrays = {k: z[k] for k in ("mean", "lower", "upper", "std")}
    else:
        from gpnarx.storage.jsonsafe import dumps_json

        r = client.post("/v1/models/m/predict", content=dumps_json({"u": u, "fs": fs, "method": "linear"}),
                        headers={"content-type": "application/json",
                                 "accept-encoding": "gzip" if kind == "gzip" else "identity"})
        r.raise_for_status()
        d = r.json()
        arrays = {k: np.asarray(d[k], dtype=np.float64) for k in ("mean", "lower", "upper", "std")}
    wall = time.perf_counter() - t0
    size = int(r.headers["content-length"])
    if kind == "gzip":
        assert r.headers.get("content-encoding") == "gzip", r.headers
    return wall, size, compute_ms(r), arrays["mean"]


RUN = ROOT / "docs" / "runs" / "bench" / "wire.txt"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=64.0, help="record length [s] (default 64)")
    ap.add_argument("--fs", type=float, default=1024.0, help="sampling frequency [Hz] (default 1024)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="8 s record, 2 repeats (smoke test)")
    ap.add_argument("--threads", type=int, default=1, help="BLAS threads (default 1, as the service)")
    ap.add_argument("--render", type=Path, default=None, metavar="PAGE",
                    help="only re-render PAGE's wire table from the stored run docs/runs/bench/wire.txt")
    args = ap.parse_args()
    if args.render:
        from gpnarx.training.pages.wire import render_page

        render_page(args.render, RUN)
        return
    if args.quick:
        args.seconds, args.repeats = 8.0, 2
    import httpx
    from threadpoolctl import threadpool_limits

    from gpnarx.service.app import create_app
    from gpnarx.service.settings import Settings

    threadpool_limits(args.threads)
    n = int(round(args.seconds * args.fs))
    u = np.random.default_rng(1).standard_normal(n)
    kinds = ("json", "gzip", "npz")
    with tempfile.TemporaryDirectory() as tmp:
        build_registry(Path(tmp), args.fs)
        app = create_app(Path(tmp), Settings(workers=1, queue_size=4, max_samples=max(n, 65536)))
        with Server(app) as srv, httpx.Client(base_url=srv.url, timeout=300) as client:
            means = {k: call(client, k, u, args.fs)[3] for k in kinds}  # warm-up (and same answers)
            walls = {k: [] for k in kinds}
            wires = {k: [] for k in kinds}
            sizes = {}
            for _ in range(args.repeats):
                for k in kinds:
                    wall, size, comp, _ = call(client, k, u, args.fs)
                    walls[k].append(wall)
                    wires[k].append(wall - comp / 1e3)
                    sizes[k] = size
    diff = max(float(np.max(np.abs(means[k] - means["json"]))) for k in kinds)
    ms = {k: 1e3 * statistics.median(v) for k, v in walls.items()}
    wire_ms = {k: 1e3 * statistics.median(v) for k, v in wires.items()}
    ratio = statistics.median(a / b for a, b in zip(wires["json"], wires["npz"]))
    print(f"{n} samples ({args.seconds:g} s at {args.fs:g} Hz), {args.repeats} repeats, median of each:")
    for k in kinds:
        print(f"  {k:5s} answer {sizes[k] / 1e6:7.3f} MB  end to end {ms[k]:8.1f} ms  wire {wire_ms[k]:8.1f} ms")
    print(f"RESULT samples={n} repeats={args.repeats} json_bytes={sizes['json']} gzip_bytes={sizes['gzip']} "
          f"npz_bytes={sizes['npz']} "
          f"json_ms={ms['json']:.1f} gzip_ms={ms['gzip']:.1f} npz_ms={ms['npz']:.1f} "
          f"json_wire_ms={wire_ms['json']:.1f} gzip_wire_ms={wire_ms['gzip']:.1f} npz_wire_ms={wire_ms['npz']:.1f} "
          f"gzip_size_ratio={sizes['json'] / sizes['gzip']:.2f} npz_size_ratio={sizes['json'] / sizes['npz']:.2f} "
          f"max_mean_diff={diff:.3g} baseline={wire_ms['json']:.1f} baseline_what=json_body_and_answer_wire_ms "
          f"ratio={ratio:.2f}")


if __name__ == "__main__":
    main()
