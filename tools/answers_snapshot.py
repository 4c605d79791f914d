"""The product's answers to a fixed set of requests, as sha256 digests: a refactor that must not change any
answer is checked by running this before and after and comparing the two files (``--compare``).

The requests: HTTP predict (linearised; Monte Carlo, 64 paths, seed 0; from measured outputs), loops, novelty
and a batch of all of them, through the FastAPI app in process; the CLI's ``predict --json`` (both methods)
and ``novelty --json``. The model is fitted here, deterministically, on a simulated single-degree-of-freedom
oscillator (u [N], y [m], fs 500 Hz) and saved as a bundle in a temporary registry, so the answers depend on the
code alone. Timing fields (``seconds``, ``elapsed``...) are left out of the digests.

    python tools/answers_snapshot.py --out before.json
    python tools/answers_snapshot.py --compare before.json
"""
from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

FS = 500.0
TIMING_KEYS = {"seconds", "elapsed", "elapsed_seconds", "wall_seconds", "fit_seconds", "request_id", "created"}


def _sdof(u, f_n=20.0, zeta=0.02):
    from scipy import signal

    wn = 2 * np.pi * f_n
    A = np.array([[0.0, 1.0], [-wn ** 2, -2 * zeta * wn]])
    B = np.array([[0.0], [1.0]])
    Ad, Bd, *_ = signal.cont2discrete((A, B, np.eye(2), np.zeros((2, 1))), 1 / FS, method="zoh")
    x, y = np.zeros(2), np.empty(len(u))
    for i, ui in enumerate(u):
        y[i] = x[0]
        x = Ad @ x + Bd[:, 0] * ui
    return y


def _registry(root: Path):
    from gpnarx.model.estimator import GPNARX
    from gpnarx.model.record import Record
    from gpnarx.storage.bundle import save_bundle

    rng = np.random.default_rng(1)
    u = rng.normal(size=2000)
    y = _sdof(u) * 1e3
    y = y + 0.02 * np.std(y) * rng.normal(size=y.size)
    model = GPNARX(ny=6, nu=6, max_train_points=400, n_restarts=0).fit([Record(u, y, FS, {"u": "N", "y": "m"})])
    save_bundle(model, root, "sdof", "1", fs=FS, units={"u": "N", "y": "m"}, training={},
                physics={"mass": 1.0, "input_gain": 1.0})
    u2 = rng.normal(size=600)
    y2 = _sdof(u2) * 1e3
    return u2, y2 + 0.02 * np.std(y2) * rng.normal(size=y2.size)


def _clean(obj):
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items() if k not in TIMING_KEYS}
    if isinstance(obj, list):
        return [_clean(v) for v in obj]
    return obj


def _digest(obj) -> str:
    return hashlib.sha256(json.dumps(_clean(obj), sort_keys=True).encode()).hexdigest()


def snapshot() -> dict:
    from fastapi.testclient import TestClient

    from gpnarx.cli.main import main
    from gpnarx.service.app import create_app
    from gpnarx.service.settings import Settings

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "reg"
        u, y = _registry(root)
        body = {"u": u.tolist(), "fs": FS}
        measured = {**body, "y": y.tolist()}
        requests = {
            "predict_linear": ("predict", {**measured, "method": "linear"}),
            "predict_mc": ("predict", {**measured, "mc_paths": 64, "seed": 0}),
            "predict_measured": ("predict", {**measured, "method": "linear", "start": "measured"}),
            "predict_rest_no_y": ("predict", {**body, "method": "linear"}),
            "loops": ("loops", {**measured, "method": "linear"}),
        }
        with TestClient(create_app(root, Settings(workers=1, queue_size=4))) as client:
            for name, (op, req) in requests.items():
                r = client.post(f"/v1/models/sdof/{op}", json=req)
                out[f"http_{name}"] = {"status": r.status_code, "sha256": _digest(r.json())}
            batch = {"requests": [{"model": "sdof", "operation": op, **req} for op, req in requests.values()]
                     + [{"model": "sdof", "operation": "predict", **body, "fs": 1.0}]}
            r = client.post("/v1/batch", json=batch)
            out["http_batch"] = {"status": r.status_code, "sha256": _digest(r.json())}
        rec = Path(tmp) / "rec.npz"
        np.savez(rec, u=u, y=y, fs=np.float64(FS))
        cli = {"cli_predict_linear": ["--method", "linear"], "cli_predict_mc": ["--mc", "64", "--seed", "0"]}
        for name, extra in cli.items():
            buf = io.StringIO()
            with contextlib.redirect_stdout(buf):
                rc = main(["predict", "--registry", str(root), "--model", "sdof", str(rec), "--json", *extra])
            out[name] = {"status": rc, "sha256": _digest(json.loads(buf.getvalue()))}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--out", help="write the digests to this JSON file")
    g.add_argument("--compare", help="compare with the digests of this JSON file; exit 1 on any difference")
    args = p.parse_args(argv)
    snap = snapshot()
    if args.out:
        Path(args.out).write_text(json.dumps(snap, indent=1, sort_keys=True))
        print(f"{len(snap)} answers written to {args.out}")
        return 0
    ref = json.loads(Path(args.compare).read_text())
    diff = sorted(k for k in set(ref) | set(snap) if ref.get(k) != snap.get(k))
    print(f"{len(snap)} answers; {len(diff)} differ" + (": " + ", ".join(diff) if diff else ""))
    return 1 if diff else 0


if __name__ == "__main__":
    sys.exit(main())
