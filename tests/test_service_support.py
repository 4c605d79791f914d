"""Shared fixtures for the service tests: a small trained Bouc-Wen registry and a real uvicorn server.

The registry is built once per test session (module-level cache, shared by every test_service*
module): a GP-NARX (ny = nu = 10, 400 training points) trained on two 10 N RMS multisines and a
30 N sweep with 5 % output noise, saved as ``boucwen`` versions 1 and 2 (novelty calibrated on
three healthy multisines, Bouc-Wen physics m = 2 kg) and ``plain`` version 1 (no physics, no
novelty calibration). Tests import what they need from here.
"""
from __future__ import annotations

import atexit
import functools
import shutil
import socket
import tempfile
import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FS = 750.0
NOISE = 0.05


def simulate(u):
    from gpnarx.training.simulators.boucwen import BoucWen

    return BoucWen().simulate(np.asarray(u, float))["y"]


def noisy(y, seed):
    rng = np.random.default_rng(seed)
    return y + NOISE * np.std(y) * rng.normal(size=y.size)


def multisine(n, seed, rms=10.0):
    from gpnarx.training import excitations as ex

    return ex.multisine(FS, rms, 5.0, 150.0, n, seed=seed)


@dataclass
class Built:
    root: Path
    model: object
    test_u: np.ndarray
    test_y: np.ndarray


#: the fixture bundles' config ``[predict] mc_paths`` (their default Monte Carlo paths in every interface)
MC_PATHS = 48


@functools.lru_cache(maxsize=1)
def built_registry() -> Built:
    """Train once per session; returns the registry folder (do not modify it: copy it)."""
    from gpnarx.model.estimator import GPNARX
    from gpnarx.model.novelty import calibrate_threshold, novelty_score, record_envelope
    from gpnarx.service.app import limit_blas_threads
    from gpnarx.storage.bundle import save_bundle
    from gpnarx.training import excitations as ex

    limit_blas_threads(1)  # as the service does; multi-threaded BLAS on small products only oversubscribes
    root = Path(tempfile.mkdtemp(prefix="gpnarx-svc-registry-"))
    atexit.register(shutil.rmtree, root, True)
    recs = []
    for k, s in enumerate((1, 2)):
        u = multisine(1024, s)
        recs.append((u, noisy(simulate(u), 100 + k)))
    us = ex.swept_sine(FS, 30.0, 5.0, 150.0, rate=53.0)
    recs.append((us, noisy(simulate(us), 200)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GPNARX(ny=10, nu=10, max_train_points=400, n_restarts=0).fit(recs)
        scores, healthy = [], []
        for s in (11, 12, 13):
            u = multisine(384, s)
            y = noisy(simulate(u), 300 + s)
            run = model.simulate(u, n_paths=48, seed=0)
            scores.append(novelty_score(y, run.mean, run.std)["score"])
            healthy.append((u, y))
    novelty = calibrate_threshold(scores, 0.01)
    # version 1 keeps the calibration of bundles written before the envelope existed
    with_envelope = {**novelty, "envelope": record_envelope(healthy)}
    physics = {"mass": 2.0, "input_gain": 1.0, "output": "displacement"}
    units = {"u": "N", "y": "m"}
    training = {"fit": 90.0, "note": "test fixture"}
    # the trained config's [predict] mc_paths: the paths of every answer whose request names none
    predict = {"predict": {"method": "mc", "mc_paths": MC_PATHS}}
    for version, nov in (("1", novelty), ("2", with_envelope)):
        save_bundle(model, root, "boucwen", version, fs=FS, units=units, physics=physics, novelty=nov,
                    training=training, extra=predict)
    save_bundle(model, root, "plain", "1", fs=FS, units=units, physics=None, novelty=None, training={},
                extra=predict)
    test_u = multisine(1024, 3)
    test_y = noisy(simulate(test_u), 400)
    return Built(root, model, test_u, test_y)


def copy_registry(dest: Path) -> Path:
    shutil.copytree(built_registry().root, dest)
    return dest


def short_record(n=96, seed=5, rms=10.0):
    u = multisine(n, seed, rms)
    return u, noisy(simulate(u), seed)


class LiveServer:
    """A real uvicorn server on 127.0.0.1 (free port) running ``app`` in a background thread.

    ``config``: ``uvicorn.Config`` keywords over the defaults (e.g. ``gpnarx serve``'s options)."""

    def __init__(self, app, **config):
        import uvicorn

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        config = uvicorn.Config(app, **{"log_level": "warning", "lifespan": "on", "timeout_keep_alive": 30, **config})
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)

    def __enter__(self):
        self.thread.start()
        t0 = time.monotonic()
        while not self.server.started:
            if not self.thread.is_alive() or time.monotonic() - t0 > 20:
                raise RuntimeError("uvicorn did not start")
            time.sleep(0.02)
        return self

    def __exit__(self, *exc):
        self.server.should_exit = True
        self.thread.join(timeout=20)
        self.sock.close()
