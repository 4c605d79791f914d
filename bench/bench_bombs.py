"""Decompression bombs against a running ``gpnarx serve``: the server's memory and liveness while it refuses them.

Two bombs of issue 50, each sent to a fresh server (``gpnarx serve --registry R --port P``, started here, so
the peak RSS ``VmHWM`` of its process measures one request):

- ``token``: a forged stream token (about 1,300 characters, signed with the public key as any client can
  when no ``GPNARX_STREAM_KEY`` is set) whose NPZ member declares 128 MiB of uint8, sent as ``state`` to
  ``POST /v1/models/MODEL/predict``; baseline: the same route continuing a legitimate token of this model;
- ``hdf5``: an HDF5 upload (about 0.5 MB) of 10 samples stored in one 512 MiB gzip chunk, sent to
  ``POST /v1/records/parse``; baseline: a legitimate HDF5 upload of 10 samples.

For each, the request's answer status and time, the server's peak RSS growth over its RSS before the
request (``*_rss_mb``) and the slowest ``GET /health/live`` answered while the request ran (``*_live_ms``),
polled back to back from another thread. ``ratio``: the bombs' largest RSS growth over the legitimate
requests' largest (floored at 1 MB): about 1 when a bomb costs what a legitimate request costs.

    python bench/bench_bombs.py [--registry /tmp/reg-bombs] [--port 8011] [--model bouc-wen] [--quick]

The registry must hold the model (``gpnarx build-defaults --registry R --only bouc-wen``). --quick: the
HDF5 bomb only (no model needed), with a 64 MiB chunk.
"""
from __future__ import annotations

import argparse
import io
import json
import os
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the bomb builders the tests use

from bomb_files import hdf5_chunk_bomb, token_bomb  # noqa: E402


def _status_kb(pid: int, key: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise KeyError(key)


def _request(url: str, data: bytes | None = None, headers: dict | None = None, timeout: float = 120.0):
    """(status, body bytes) of one request."""
    req = urllib.request.Request(url, data=data, headers=headers or {}, method="POST" if data is not None else "GET")
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def _multipart(name: str, data: bytes) -> tuple[bytes, dict]:
    b = uuid.uuid4().hex
    body = (f"--{b}\r\nContent-Disposition: form-data; name=\"files\"; filename=\"{name}\"\r\n"
            f"Content-Type: application/octet-stream\r\n\r\n").encode() + data + f"\r\n--{b}--\r\n".encode()
    return body, {"content-type": f"multipart/form-data; boundary={b}"}


class Server:
    """``gpnarx serve`` on ``port`` over ``registry``, in its own process."""

    def __init__(self, registry: str, port: int):
        self.url = f"http://127.0.0.1:{port}"
        self.proc = subprocess.Popen([sys.executable, "-m", "gpnarx", "serve", "--registry", registry, "--port",
                                      str(port), "--workers", "1"], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL,
                                     env={k: v for k, v in os.environ.items() if k != "GPNARX_STREAM_KEY"})

    def wait(self, ready: bool, timeout: float = 180.0) -> None:
        path = "/health/ready" if ready else "/health/live"
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                raise SystemExit(f"gpnarx serve exited with {self.proc.returncode}")
            try:
                if _request(self.url + path, timeout=2)[0] == 200:
                    return
            except OSError:
                pass
            time.sleep(0.3)
        raise SystemExit(f"gpnarx serve was not {'ready' if ready else 'live'} in {timeout:.0f} s")

    def measure(self, path: str, data: bytes, headers: dict) -> dict:
        """status, seconds, peak RSS growth [MB] and slowest /health/live [ms] of one request."""
        pid = self.proc.pid
        rss0 = _status_kb(pid, "VmRSS")
        hwm0 = _status_kb(pid, "VmHWM")
        slowest, stop = [0.0], threading.Event()

        def poll():
            while not stop.is_set():
                t = time.perf_counter()
                _request(self.url + "/health/live", timeout=60)
                slowest[0] = max(slowest[0], time.perf_counter() - t)

        poller = threading.Thread(target=poll, daemon=True)
        poller.start()
        t0 = time.perf_counter()
        status, body = _request(self.url + path, data, headers)
        took = time.perf_counter() - t0
        stop.set()
        poller.join()
        hwm = _status_kb(pid, "VmHWM")
        grew = max(hwm - rss0, 0) if hwm > hwm0 else max(_status_kb(pid, "VmRSS") - rss0, 0)
        return {"status": status, "s": took, "rss_mb": grew / 1024.0, "live_ms": slowest[0] * 1e3,
                "body": body[:300]}

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def _json(obj) -> tuple[bytes, dict]:
    return json.dumps(obj).encode(), {"content-type": "application/json"}


def token_case(registry: str, port: int, model: str) -> tuple[dict, dict, int]:
    srv = Server(registry, port)
    try:
        srv.wait(ready=True)
        info = json.loads(_request(f"{srv.url}/v1/models/{model}")[1])
        u = np.sin(np.arange(400) / 7.0).tolist()
        first = {"u": u, "fs": info["fs"], "method": "mc",
                 "mc_paths": 64, "seed": 0, "return_state": True}
        path = f"/v1/models/{model}/predict"
        status, body = _request(srv.url + path, *_json(first))
        if status != 200:
            raise SystemExit(f"the first chunk failed: {status} {body[:300]!r}")
        legit = srv.measure(path, *_json({**first, "state": json.loads(body)["state"]}))
        bomb = token_bomb(model, info["version"])
        return legit, srv.measure(path, *_json({**first, "state": bomb})), len(bomb)
    finally:
        srv.stop()


def hdf5_case(registry: str, port: int, chunk: int) -> tuple[dict, dict, int]:
    import h5py

    small = io.BytesIO()
    with h5py.File(small, "w") as f:
        f.create_dataset("u", data=np.arange(10.0), chunks=(10,), compression="gzip")
        f.create_dataset("fs", data=100.0)
    srv = Server(registry, port)
    try:
        srv.wait(ready=False)
        legit = srv.measure("/v1/records/parse", *_multipart("ok.h5", small.getvalue()))
        bomb = hdf5_chunk_bomb(chunk=chunk)
        return legit, srv.measure("/v1/records/parse", *_multipart("bomb.h5", bomb)), len(bomb)
    finally:
        srv.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--registry", default="/tmp/reg-bombs")
    ap.add_argument("--port", type=int, default=8011)
    ap.add_argument("--model", default="bouc-wen")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    Path(args.registry).mkdir(parents=True, exist_ok=True)
    fields, legit_rss, bomb_rss = {}, [], []
    cases = [("hdf5", lambda: hdf5_case(args.registry, args.port, (1 << 23) if args.quick else (1 << 26)))]
    if not args.quick:
        cases.insert(0, ("token", lambda: token_case(args.registry, args.port, args.model)))
    for name, run in cases:
        legit, bomb, size = run()
        print(f"{name}: bomb of {size} bytes -> {bomb['status']} in {bomb['s']:.2f} s: {bomb['body']!r}",
              file=sys.stderr)
        fields.update({f"{name}_bytes": size, f"{name}_status": bomb["status"], f"{name}_s": f"{bomb['s']:.3f}",
                       f"{name}_rss_mb": f"{bomb['rss_mb']:.1f}", f"{name}_live_ms": f"{bomb['live_ms']:.1f}",
                       f"{name}_legit_rss_mb": f"{legit['rss_mb']:.1f}",
                       f"{name}_legit_live_ms": f"{legit['live_ms']:.1f}"})
        legit_rss.append(legit["rss_mb"])
        bomb_rss.append(bomb["rss_mb"])
    fields["baseline"] = f"{max(legit_rss):.1f}"
    fields["baseline_what"] = "peak_RSS_growth_MB_of_a_legitimate_request_on_the_same_route"
    fields["ratio"] = f"{max(bomb_rss) / max(max(legit_rss), 1.0):.2f}"
    print("RESULT " + " ".join(f"{k}={v}" for k, v in fields.items()))


if __name__ == "__main__":
    main()
