"""Deployment files: the Dockerfile's steps, deploy/compose.yaml and deploy/k8s/ (issue 26).

There is no container engine here, so the Dockerfile is checked in two ways: its structure (a build
stage that makes wheels, a runtime stage that installs the gpnarx wheel from them, a non-root
user, the health check on /health/ready) and its steps run directly: the sources the build stage
copies are copied to a temporary folder, the wheel is built from them, installed into a fresh
venv, and the console script and the image's command answer ``--help``. The compose file and the
Kubernetes manifests are parsed and checked against the service: probe paths are routes of the
committed OpenAPI document, the port is the one ``gpnarx serve`` is told to use, replicas are 2,
and every environment variable is one the package reads (or a standard AWS variable).
"""
from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import pytest
from venv_support import make_venv

yaml = pytest.importorskip("yaml")

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
AWS_ENV = {"AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_SESSION_TOKEN", "AWS_DEFAULT_REGION", "AWS_REGION",
           "AWS_ENDPOINT_URL", "AWS_PROFILE"}
OTHER_ENV = {"OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "MPLBACKEND"}


# ---------------------------------------------------------------------------------------- helpers
def dockerfile_stages() -> list[dict]:
    """The Dockerfile as stages: {"from", "name", "instructions": [(KEYWORD, argument text)]}."""
    text = re.sub(r"\\\n", " ", (ROOT / "Dockerfile").read_text())
    stages = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        kw, _, arg = line.partition(" ")
        kw, arg = kw.upper(), arg.strip()
        if kw == "FROM":
            m = re.match(r"(\S+)(?:\s+AS\s+(\S+))?$", arg, re.IGNORECASE)
            stages.append({"from": m.group(1), "name": m.group(2), "instructions": []})
        else:
            stages[-1]["instructions"].append((kw, arg))
    return stages


def _json_or_shell(arg: str) -> list[str]:
    return json.loads(arg) if arg.startswith("[") else shlex.split(arg)


def image_cmd() -> list[str]:
    return _json_or_shell([a for k, a in dockerfile_stages()[-1]["instructions"] if k == "CMD"][-1])


def image_env() -> dict:
    env = {}
    for k, a in dockerfile_stages()[-1]["instructions"]:
        if k == "ENV":
            for item in shlex.split(a):
                name, _, value = item.partition("=")
                env[name] = value
    return env


def serve_port(cmd: list[str]) -> int:
    assert cmd[:2] == ["gpnarx", "serve"], cmd
    assert cmd[cmd.index("--host") + 1] == "0.0.0.0", "a container must listen on all interfaces"
    return int(cmd[cmd.index("--port") + 1])


def routes() -> set[str]:
    return set(json.loads((ROOT / "openapi" / "openapi.json").read_text())["paths"])


def env_names_read_by_the_package() -> set[str]:
    names = set()
    for folder in ("model", "operations", "storage", "training", "service", "cli", "gpnarx"):
        for f in (ROOT / folder).rglob("*.py"):
            names |= set(re.findall(r"\bGPNARX_[A-Z][A-Z_]*[A-Z]\b", f.read_text()))
    return names


def check_env_names(names, where):
    known = env_names_read_by_the_package()
    unknown = {n for n in names if n not in known and n not in AWS_ENV and n not in OTHER_ENV}
    assert not unknown, f"{where}: environment variables no part of gpnarx reads: {sorted(unknown)}"


def k8s_docs() -> dict:
    docs = {}
    for f in sorted((DEPLOY / "k8s").glob("*.yaml")):
        for d in yaml.safe_load_all(f.read_text()):
            if d:
                docs.setdefault(d["kind"], []).append(d)
    return docs


# ---------------------------------------------------------------------------------------- Dockerfile
def test_dockerfile_builds_a_wheel_and_installs_it_in_a_non_root_runtime_stage():
    stages = dockerfile_stages()
    assert len(stages) == 2, [s["from"] for s in stages]
    build, run = stages
    assert build["name"], "the build stage is named, so the runtime stage can copy from it"
    wheel_steps = [a for k, a in build["instructions"] if k == "RUN" and "pip wheel" in a]
    assert len(wheel_steps) == 1 and re.search(r"-w\s+/wheels\b", wheel_steps[0]), wheel_steps
    assert any(k == "COPY" and f"--from={build['name']}" in a and "/wheels" in a for k, a in run["instructions"])
    installs = [a for k, a in run["instructions"] if k == "RUN" and "pip install" in a]
    assert len(installs) == 1 and "--no-index" in installs[0] and "--find-links" in installs[0], installs
    assert "gpnarx" in installs[0]
    for _, a in build["instructions"] + run["instructions"]:
        assert not re.search(r"pip install\s+(-\S+\s+)*-e\b", a), f"editable install: {a}"
    users = [a for k, a in run["instructions"] if k == "USER"]
    kws = [k for k, _ in run["instructions"]]
    assert users and users[-1] not in ("root", "0") and kws.index("USER") < kws.index("CMD")
    health = [a for k, a in run["instructions"] if k == "HEALTHCHECK"]
    assert health and "/health/ready" in health[0] and "/health/ready" in routes()
    assert f":{serve_port(image_cmd())}/health/ready" in health[0]
    assert any(k == "EXPOSE" and a == str(serve_port(image_cmd())) for k, a in run["instructions"])


def _clean_env() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP")}
    env.update(PYTHONNOUSERSITE="1", PIP_DISABLE_PIP_VERSION_CHECK="1", PIP_NO_INPUT="1")
    return env


def _run(cmd, cwd, timeout=180) -> subprocess.CompletedProcess:
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, env=_clean_env(), capture_output=True, text=True,
                          timeout=timeout)
    assert proc.returncode == 0, f"{cmd} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc


def _can_build_offline() -> bool:
    try:
        return int(metadata.version("setuptools").split(".")[0]) >= 68 and bool(metadata.version("wheel"))
    except (metadata.PackageNotFoundError, ValueError):
        return False


def test_dockerfile_steps_build_the_wheel_install_it_and_run_the_image_command(tmp_path):
    """The build stage's COPY lines and `pip wheel`, then the runtime stage's install, run here: only
    what the Dockerfile copies goes into the wheel, and the installed command answers."""
    build, run = dockerfile_stages()
    src = tmp_path / "src"
    src.mkdir()
    for kw, arg in build["instructions"]:
        if kw != "COPY":
            continue
        *sources, dest = shlex.split(arg)
        for s in sources:
            target = src / dest / Path(s).name if dest.endswith("/") else src / dest
            if (ROOT / s).is_dir():
                shutil.copytree(ROOT / s, target, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
            else:
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(ROOT / s, target)
    wheels = tmp_path / "wheels"
    wheel_cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", wheels, src]
    if _can_build_offline():
        wheel_cmd.insert(4, "--no-build-isolation")
    _run(wheel_cmd, cwd=tmp_path, timeout=240)
    built = list(wheels.glob("gpnarx-*.whl"))
    assert len(built) == 1, built
    # a fresh venv; it sees the running environment's packages (the user's venv or the machine's
    # interpreter, tests/venv_support.py) so nothing is downloaded, and gpnarx must then resolve to
    # the wheel installed in it, not to the checkout
    env_dir = tmp_path / "venv"
    py = make_venv(env_dir, with_pip=True)
    install = [a for k, a in run["instructions"] if k == "RUN" and "pip install" in a][0]
    requirement = re.search(r'"(gpnarx[^"]*)"|\b(gpnarx\[[^\]]*\]|gpnarx)\b', install)
    requirement = requirement.group(1) or requirement.group(2)
    # the wheel itself (forced: the checkout's editable gpnarx of the same version is visible), then the
    # Dockerfile's requirement with its extras, which must resolve without an index
    _run([py, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--force-reinstall", built[0]], cwd=tmp_path)
    extras = _run([py, "-m", "pip", "install", "--no-index", "--find-links", wheels, requirement], cwd=tmp_path)
    assert "does not provide the extra" not in extras.stdout + extras.stderr, extras.stderr
    where = _run([py, "-c", "import gpnarx, gpnarx.service.app, gpnarx.storage.bundle, gpnarx.cli.main; "
                            "print(gpnarx.__file__)"], cwd=tmp_path).stdout.strip()
    assert where.startswith(str(env_dir)), where
    exe = env_dir / "bin" / "gpnarx"
    helped = _run([exe, "--help"], cwd=tmp_path).stdout
    assert "predict-many" in helped and "serve" in helped
    cmd = image_cmd()
    assert "--port" in _run([env_dir / "bin" / cmd[0], *cmd[1:], "--help"], cwd=tmp_path).stdout
    assert "--registry" in _run([exe, "build-defaults", "--help"], cwd=tmp_path).stdout
    configs = _run([py, "-c", "from gpnarx.configs import shipped_config_names; print(sorted(shipped_config_names()))"],
                   cwd=tmp_path).stdout
    assert "bouc-wen" in configs  # shipped configs are package data of the wheel


# ---------------------------------------------------------------------------------------- compose
def test_compose_runs_two_replicas_on_one_registry_with_a_readiness_healthcheck():
    doc = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
    svc = doc["services"]["gpnarx"]
    assert svc["deploy"]["replicas"] == 2
    cmd = svc.get("command") or image_cmd()
    port = serve_port(cmd)
    assert port == serve_port(image_cmd())
    host_ports = [p for p in svc["ports"] if str(p).endswith(f":{port}")]
    assert host_ports, svc["ports"]
    host = re.sub(r"\$\{[A-Z_]+:-([^}]*)\}", r"\1", str(host_ports[0])).rpartition(":")[0]  # defaults filled in
    lo, _, hi = host.partition("-")
    assert int(hi or lo) - int(lo) + 1 >= svc["deploy"]["replicas"], "one host port per replica"
    test = " ".join(svc["healthcheck"]["test"])
    assert f"127.0.0.1:{port}/health/ready" in test and "/health/ready" in routes()
    env = svc["environment"]
    check_env_names(env, "compose.yaml gpnarx")
    assert {"GPNARX_REGISTRY", "GPNARX_REGISTRY_POLL", "AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"} <= set(env)
    for secret in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "GPNARX_API_KEY"):
        assert env.get(secret) is None, f"{secret} is passed through from the environment, not written here"
    # the registry default is the mounted volume, the image's default registry folder
    default_registry = re.fullmatch(r"\$\{GPNARX_REGISTRY:-([^}]+)\}", env["GPNARX_REGISTRY"]).group(1)
    assert default_registry == image_env()["GPNARX_REGISTRY"]
    mounts = [v.split(":") for v in svc["volumes"]]
    assert any(m[1] == default_registry and m[0] in (doc.get("volumes") or {}) for m in mounts), mounts
    # the optional Dask services use the same image and reach the scheduler by its service name
    sched, worker = doc["services"]["dask-scheduler"], doc["services"]["dask-worker"]
    assert sched["image"] == worker["image"] == svc["image"]
    sport = sched["command"][sched["command"].index("--port") + 1]
    assert f"tcp://dask-scheduler:{sport}" in worker["command"] and worker["deploy"]["replicas"] == 2
    check_env_names(worker.get("environment") or {}, "compose.yaml dask-worker")


# ---------------------------------------------------------------------------------------- Kubernetes
def test_k8s_deployment_probes_replicas_env_and_service_match_the_service():
    docs = k8s_docs()
    (dep,), (svc,), (secret,) = docs["Deployment"], docs["Service"], docs["Secret"]
    assert dep["spec"]["replicas"] == 2
    pod = dep["spec"]["template"]
    assert dep["spec"]["selector"]["matchLabels"].items() <= pod["metadata"]["labels"].items()
    (c,) = pod["spec"]["containers"]
    port = serve_port(c.get("command") or image_cmd())
    (cport,) = c["ports"]
    assert cport["containerPort"] == port
    ready, live = c["readinessProbe"]["httpGet"], c["livenessProbe"]["httpGet"]
    assert ready["path"] == "/health/ready" and live["path"] == "/health/live"
    assert {ready["path"], live["path"]} <= routes()
    for probe in ("readinessProbe", "livenessProbe", "startupProbe"):
        if probe in c:
            assert c[probe]["httpGet"]["port"] in (cport.get("name"), port), probe
    sec = pod["spec"]["securityContext"]
    assert sec["runAsNonRoot"] is True and sec["runAsUser"] != 0
    names = [e["name"] for e in c["env"]]
    assert len(names) == len(set(names))
    check_env_names(names, "k8s deployment")
    by_name = {e["name"]: e for e in c["env"]}
    # registry URL and credentials come from the Secret, never as literal values
    for name in ("GPNARX_REGISTRY", "AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"):
        ref = by_name[name]["valueFrom"]["secretKeyRef"]
        assert ref["name"] == secret["metadata"]["name"] and ref["key"] in secret["stringData"], name
        assert not ref.get("optional")
    for e in c["env"]:
        ref = (e.get("valueFrom") or {}).get("secretKeyRef")
        assert ref is None or ref["name"] == secret["metadata"]["name"], e
        if e["name"].startswith("AWS_SECRET") or e["name"] == "GPNARX_API_KEY":
            assert "value" not in e, f"{e['name']} must come from the Secret"
    assert secret["stringData"]["registry-url"].startswith(("s3://", "gs://"))
    # the Service reaches the pods on the container's port
    assert svc["spec"]["selector"].items() <= pod["metadata"]["labels"].items()
    (sp,) = svc["spec"]["ports"]
    assert sp["targetPort"] in (cport.get("name"), port)
    # kustomization lists files that exist, and not the example Secret
    (kust,) = docs["Kustomization"]
    assert all((DEPLOY / "k8s" / r).is_file() for r in kust["resources"])
    assert "secret.example.yaml" not in kust["resources"]
