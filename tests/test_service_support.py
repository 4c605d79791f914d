"""Shared fixtures for the service tests: a small trained Bouc-Wen registry and a real uvicorn server.

The registry is built once per test session (tests/session_cache.py: one build shared by every
pytest-xdist worker and every module): a GP-NARX (ny = nu = 10, 400 training points) trained on two
10 N RMS multisines and a 30 N sweep with 5 % output noise, saved as ``boucwen`` versions 1 and 2 (novelty calibrated on
three healthy multisines, Bouc-Wen physics m = 2 kg) and ``plain`` version 1 (no physics, no
novelty calibration). Tests import what they need from here.
"""
from __future__ import annotations

import functools
import shutil
import socket
import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from session_cache import build_once, digest

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
    """The registry, trained once per session (tests/session_cache.py: the first pytest-xdist worker to
    ask builds it, the others wait and read it); do not modify it: copy it. ``model`` is the bundle
    ``plain/1`` as loaded, the same arrays every served version holds."""
    from gpnarx.storage.bundle import load_bundle

    root = build_once("svc-registry", digest(Path(__file__)), _build_registry)
    test = np.load(root / "test_record.npz")
    return Built(root / "registry", load_bundle(root / "registry" / "plain" / "1").model, test["u"], test["y"])


def _build_registry(folder: Path) -> None:
    """Train the fixture model and write its bundles into ``folder/registry`` (the test record beside)."""
    from gpnarx.model.estimator import GPNARX
    from gpnarx.model.novelty import calibrate_threshold, novelty_score, record_envelope
    from gpnarx.service.app import limit_blas_threads
    from gpnarx.storage.bundle import save_bundle
    from gpnarx.training import excitations as ex

    limit_blas_threads(1)  # as the service does; multi-threaded BLAS on small products only oversubscribes
    root = folder / "registry"
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
    np.savez(folder / "test_record.npz", u=test_u, y=noisy(simulate(test_u), 400))


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
