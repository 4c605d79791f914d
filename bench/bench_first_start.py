"""First start: ``gpnarx serve`` on an empty default registry, timed from outside as a user sees it.

Product: ``python -m gpnarx serve --port P`` with ``GPNARX_REGISTRY`` an empty temporary folder
and ``GPNARX_DEFAULTS`` the defaults to build (``--defaults``; default ``bouc-wen``, ``all`` for
every default). Timed from the launch: seconds to ``/health/live`` 200 (``live_s``), to
``/health/ready`` 200, i.e. the first model loaded (``ready_s``), to the first predict answered
(``predict_s``: POST /v1/models/bouc-wen/predict, a 256-sample 35.59 Hz 10 N sine, 64 paths,
sent as soon as ready) and to each default loaded (``loaded_NAME_s``, read from
``/health/ready``'s ``startup`` every 0.5 s).

Baseline, same run, the previous code path (``baseline=``): the first start trained every missing
default before the server started, with the previous default-build settings (the shipped config,
128 Monte Carlo paths, the config's own report method). Here, for the same defaults: a child
process that trains them that way into another empty folder, then ``gpnarx serve --registry``
over it; seconds from the launch to ``/health/live`` 200 (which is also ready) and to the same
first predict. With one default this is a lower bound of the previous first start, which built
all four before opening its port. ``ratio`` = baseline / product seconds to ``/health/live``;
``predict_ratio`` = baseline / product seconds to the first predict. Product first, then the
baseline (minutes each): the load average at each start is printed; both move with other jobs.
The target for the port is ``--live-target`` seconds (default 10): ``live_target_s=`` and
``live_met=1|0`` on the RESULT line (tests/test_first_start.py checks only that the port opens
before the defaults are built, not how fast).

``--baseline serial``: the baseline is instead the same ``gpnarx serve`` building one default at a time
(``--build-jobs 1``, the start path before builds ran in parallel); ``ratio`` = its seconds until every
default is loaded (``done_s``) / the product's. ``--baseline none``: the product only (``ratio=`` is then
absent). ``--bert-data DIR``: the lab records the servers see (``GPNARX_BERT_DATA``; an empty folder
leaves the real-data defaults out, as on a machine without them). The RESULT line gives the cores, the
1-minute load average at each start and end (the machine's other work moves every figure) and the
commit measured.

    python bench/bench_first_start.py [--defaults bouc-wen|all|NAME,...] [--timeout S] [--live-target S]
        [--baseline previous|serial|none] [--bert-data DIR]
"""
from __future__ import annotations

import argparse
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OLD_BUILD = """
import sys
from gpnarx.configs import shipped_config
from gpnarx.training.pipeline import train
for name in sys.argv[2].split(","):
    train(shipped_config(name), sys.argv[1], mc_paths=128)
"""


def _port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def _get(url):
    try:
        return httpx.get(url, timeout=5)
    except httpx.HTTPError:
        return None


def _predict(url) -> int:
    u = (10.0 * np.sin(2 * np.pi * 35.59 * np.arange(256) / 750.0)).tolist()
    r = httpx.post(url + "/v1/models/bouc-wen/predict", json={"u": u, "fs": 750.0, "mc_paths": 64, "seed": 0},
                   timeout=300)
    return r.status_code


def _stop(proc):
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:  # pragma: no cover
            proc.kill()
            proc.wait()


def product(names, work: Path, timeout: float, env, jobs: int | None = None, tag: str = "product") -> dict:
    """``gpnarx serve`` on an empty default registry (``--build-jobs jobs`` when given), timed from outside."""
    reg = work / f"{tag}-registry"
    port = _port()
    url = f"http://127.0.0.1:{port}"
    env = dict(env, GPNARX_REGISTRY=str(reg), GPNARX_DEFAULTS=",".join(names))
    out = {"load": os.getloadavg()[0]}
    t0 = time.monotonic()
    extra = [] if jobs is None else ["--build-jobs", str(jobs)]
    with open(work / f"{tag}.log", "w") as log:
        proc = subprocess.Popen([sys.executable, "-m", "gpnarx", "serve", "--port", str(port), "--log-level",
                                 "warning", *extra], env=env, stdout=log, stderr=log, cwd=str(work))
        try:
            while (r := _get(url + "/health/live")) is None or r.status_code != 200:
                if proc.poll() is not None or time.monotonic() - t0 > timeout:
                    raise SystemExit(f"the server did not answer /health/live (see {work / (tag + '.log')})")
                time.sleep(0.05)
            out["live_s"] = time.monotonic() - t0
            seen = set()
            while True:
                r = _get(url + "/health/ready")
                now = time.monotonic() - t0
                if r is not None:
                    st = r.json().get("startup") or {}
                    for n in st.get("built", []):
                        if n not in seen:
                            seen.add(n)
                            out[f"loaded_{n}_s"] = now
                    for n in st.get("failed", []):
                        out.setdefault(f"failed_{n}_s", now)
                    if r.status_code == 200 and "ready_s" not in out:
                        out["ready_s"] = now
                        status = _predict(url) if "bouc-wen" in st.get("built", []) else None
                        out["predict_s"] = time.monotonic() - t0
                        out["predict_status"] = status
                    if st.get("done"):
                        out["done_s"] = now
                        out["load_end"] = os.getloadavg()[0]
                        break
                if now > timeout:
                    raise SystemExit(f"the defaults were not all built within {timeout} s")
                time.sleep(0.5)
        finally:
            _stop(proc)
    return out


def baseline(names, work: Path, timeout: float, env) -> dict:
    reg = work / "baseline-registry"
    reg.mkdir()
    port = _port()
    url = f"http://127.0.0.1:{port}"
    out = {"load": os.getloadavg()[0]}
    t0 = time.monotonic()
    with open(work / "baseline.log", "w") as log:
        subprocess.run([sys.executable, "-c", OLD_BUILD, str(reg), ",".join(names)], env=env, stdout=log,
                       stderr=log, check=True, timeout=timeout, cwd=str(work))
        out["build_s"] = time.monotonic() - t0
        proc = subprocess.Popen([sys.executable, "-m", "gpnarx", "serve", "--registry", str(reg), "--port",
                                 str(port), "--log-level", "warning"], env=env, stdout=log, stderr=log, cwd=str(work))
        try:
            while (r := _get(url + "/health/live")) is None or r.status_code != 200:
                if proc.poll() is not None:
                    raise SystemExit(f"the baseline server exited (see {work / 'baseline.log'})")
                time.sleep(0.05)
            out["live_s"] = time.monotonic() - t0
            out["predict_status"] = _predict(url) if "bouc-wen" in names else None
            out["predict_s"] = time.monotonic() - t0
        finally:
            _stop(proc)
    return out


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=str(ROOT), capture_output=True, text=True,
                              check=True).stdout.strip() or "unknown"
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--defaults", default="bouc-wen", help="defaults to build (comma-separated, or 'all')")
    ap.add_argument("--timeout", type=float, default=3600.0, help="give up after this many seconds per side")
    ap.add_argument("--live-target", type=float, default=10.0,
                    help="seconds within which /health/live should answer (live_met= on the RESULT line)")
    ap.add_argument("--baseline", choices=("previous", "serial", "none"), default="previous",
                    help="previous: build then serve (default); serial: serve with --build-jobs 1; none: no baseline")
    ap.add_argument("--bert-data", default=None,
                    help="GPNARX_BERT_DATA for the servers (an empty folder: no real-data defaults)")
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    if args.bert_data is not None:
        os.environ["GPNARX_BERT_DATA"] = str(Path(args.bert_data).resolve())
    from gpnarx.cli.startup import available_cores, build_jobs
    from gpnarx.training.defaults import default_names, plan_defaults

    names = list(default_names("" if args.defaults == "all" else args.defaults))
    work = Path(tempfile.mkdtemp(prefix="gpnarx-first-start-"))
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("GPNARX_API_KEY", None)
    names = plan_defaults(work / "none", names)["missing"]  # bert-real only with its lab records
    b = None
    try:
        p = product(names, work, args.timeout, env)
        print(f"product (serve on an empty registry, load {p['load']:.1f}): " + ", ".join(
            f"{k} {v:.1f}" for k, v in p.items() if k.endswith("_s")), flush=True)
        if args.baseline == "previous":
            b = baseline(names, work, args.timeout, env)
        elif args.baseline == "serial":
            b = product(names, work, args.timeout, env, jobs=1, tag="serial")
        if b is not None:
            print(f"baseline {args.baseline} (load {b['load']:.1f}): " + ", ".join(
                f"{k} {v:.1f}" for k, v in b.items() if k.endswith("_s")), flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    fields = {"defaults": ",".join(names), "live_s": p["live_s"], "live_target_s": args.live_target,
              "live_met": int(p["live_s"] <= args.live_target), "ready_s": p.get("ready_s"),
              "predict_s": p.get("predict_s"), "predict_status": p.get("predict_status"), "done_s": p.get("done_s"),
              **{k: v for k, v in p.items() if k.startswith(("loaded_", "failed_"))},
              "build_jobs": build_jobs(len(names)), "cores": available_cores(), "load": p["load"],
              "load_end": p.get("load_end"), "bert_data": int(any(n.startswith("bert-real") for n in names)),
              "commit": _commit()}
    if args.baseline == "previous":
        fields.update({"baseline": b["live_s"], "baseline_what": "build_then_serve_live_s",
                       "baseline_predict_s": b.get("predict_s"), "baseline_load": b["load"],
                       "ratio": b["live_s"] / p["live_s"],
                       "predict_ratio": (b["predict_s"] / p["predict_s"]) if p.get("predict_s") and b.get("predict_s")
                       else None})
    elif args.baseline == "serial":
        fields.update({"baseline": b.get("done_s"), "baseline_what": "serve_build_jobs_1_done_s",
                       "baseline_load": b["load"], "baseline_load_end": b.get("load_end"),
                       "ratio": (b["done_s"] / p["done_s"]) if b.get("done_s") and p.get("done_s") else None})
    print("RESULT " + " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in fields.items()))


if __name__ == "__main__":
    main()
