"""requirements.lock (the Docker image's dependencies, pinned with hashes) covers pyproject's core and the
image's extras (s3, dask, train), each pin carrying at least one sha256 hash."""
import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
IMAGE_EXTRAS = ("s3", "dask", "train")


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _req_name(req: str) -> str:
    return _norm(re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", req).group(1))


def locked() -> dict:
    pins, current = {}, None
    for line in (ROOT / "requirements.lock").read_text().splitlines():
        m = re.match(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==(\S+)", line)
        if m:
            current = _norm(m.group(1))
            pins[current] = {"version": m.group(2), "hashes": 0}
        elif current and "--hash=sha256:" in line:
            pins[current]["hashes"] += 1
    return pins


def test_lock_covers_the_core_and_the_image_extras():
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    wanted = [r for r in meta["dependencies"]]
    for extra in IMAGE_EXTRAS:
        wanted += [r for r in meta["optional-dependencies"][extra] if not r.startswith("gpnarx")]
    pins = locked()
    missing = sorted({_req_name(r) for r in wanted} - set(pins))
    assert not missing, f"requirements.lock lacks {missing}: regenerate it (docs/deploy.md)"
    assert all(p["hashes"] >= 1 for p in pins.values()), [n for n, p in pins.items() if not p["hashes"]]
    assert "gpnarx" not in pins  # the image builds gpnarx itself


def test_dockerfile_installs_from_the_lock_with_hashes():
    text = (ROOT / "Dockerfile").read_text()
    assert "COPY requirements.lock" in text and "--require-hashes --no-deps -r requirements.lock" in text
