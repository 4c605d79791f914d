"""Versioned model bundles and the registry that holds them.

Layout: ``REGISTRY/NAME/VERSION/`` with ``manifest.json`` and one ``.npy`` file per array.
The manifest holds the schema version, name, version, creation time, lags, kernel and
hyperparameters, fs, units, physical constants, novelty calibration, training metrics, package
versions and the sha256 of every array file. Loading never executes code from a bundle: arrays are
read with ``allow_pickle=False`` and the kernel is rebuilt from a whitelist of types. A bundle
whose manifest or checksums do not verify is refused with a ``BundleError`` naming the file.
Writes are atomic: a bundle is written into a hidden temporary folder and renamed into place, so a
killed run leaves no partial version visible (``Registry.scan`` and ``next_version`` skip hidden
folders). Such a leftover ``NAME/.tmp-VERSION-*`` folder is removed by the next ``save_bundle`` of
the same model name once it is older than ``STALE_TMP_SECONDS`` (one hour, so a write in progress
in another process is never touched), or at once with ``remove_stale_temps(registry, 0)``.
Versions are positive integers, increasing; an existing version is never overwritten.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import re
import shutil
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .discrepancy import check_discrepancy
from .envelope import check_envelope
from .estimator import GPNARX
from .gp import ExactPosterior, SparsePosterior
from .kernels import DEFAULT_CONSTANT_CAP, kernel_from_dict
from .scaling import Standardizer

SCHEMA_VERSION = 2  # what save_bundle writes; older manifests are migrated on load (MIGRATIONS)
MANIFEST = "manifest.json"
MANIFEST_SUM = "manifest.sha256"  # sha256 of manifest.json: an edited manifest is refused too
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
VERSION_RE = re.compile(r"^[1-9][0-9]{0,8}$")
MAX_MANIFEST_BYTES = 4 * 1024 * 1024
TMP_PREFIX = ".tmp-"  # hidden temporary folder of a bundle being written: NAME/.tmp-VERSION-XXXX
STALE_TMP_SECONDS = 3600.0  # a temporary folder untouched this long is a killed write's leftover
REQUIRED_KEYS = ("schema_version", "name", "version", "created", "lags", "kernel", "noise_var", "mode",
                 "fs", "units", "files", "estimator")


class BundleError(ValueError):
    """A bundle is missing, malformed or fails its checksums."""


class BundleWarning(UserWarning):
    """A bundle loads and serves, but should be retrained (the message says why)."""


def check_name(name: str, what: str = "model name") -> str:
    if not isinstance(name, str) or not NAME_RE.match(name) or ".." in name:
        raise BundleError(f"{what} {name!r} is invalid: use 1-64 letters, digits, '_', '-', '.' "
                          "starting with a letter or digit")
    return name


def check_version(version) -> str:
    v = str(version)
    if not VERSION_RE.match(v):
        raise BundleError(f"version {version!r} is invalid: use a positive integer")
    return v


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _package_versions() -> dict:
    import platform

    import scipy

    return {"python": platform.python_version(), "numpy": np.__version__, "scipy": scipy.__version__,
            "gpnarx": _own_version()}


def _own_version() -> str:
    try:
        from importlib.metadata import version

        return version("gpnarx")
    except Exception:  # not installed (running from a checkout)
        return "0+unknown"


def model_arrays(model: GPNARX) -> dict:
    """Every array needed to predict, by file stem."""
    arrays = {
        "x_mean": model.x_scaler_.mean_, "x_scale": model.x_scaler_.scale_,
        "y_mean": model.y_scaler_.mean_, "y_scale": model.y_scaler_.scale_,
        "theta": model.theta_,
    }
    for k, v in model.posterior_.arrays().items():
        arrays[f"posterior_{k}"] = v
    return arrays


@dataclass
class Bundle:
    """A loaded bundle: the fitted model plus its manifest."""

    model: GPNARX
    manifest: dict
    path: Path

    @property
    def name(self) -> str:
        return self.manifest["name"]

    @property
    def version(self) -> str:
        return str(self.manifest["version"])

    @property
    def fs(self) -> float:
        return float(self.manifest["fs"])


def next_version(registry: Path, name: str) -> str:
    d = Path(registry) / check_name(name)
    existing = [int(p.name) for p in d.iterdir() if p.is_dir() and VERSION_RE.match(p.name)] if d.is_dir() else []
    return str(max(existing, default=0) + 1)


def remove_stale_temps(registry, older_than: float = STALE_TMP_SECONDS, name: str | None = None) -> list[Path]:
    """Remove temporary folders (``NAME/.tmp-*``) left by killed writes; returns the removed paths.

    Only folders whose modification time is at least ``older_than`` seconds old are removed (a write
    in progress in another process keeps touching its folder). ``name`` limits it to one model.
    """
    import time

    registry = Path(registry)
    dirs = [registry / check_name(name)] if name is not None else (
        [d for d in registry.iterdir() if d.is_dir() and not d.name.startswith(".")] if registry.is_dir() else [])
    now, removed = time.time(), []
    for d in dirs:
        if not d.is_dir():
            continue
        for t in d.iterdir():
            try:
                if t.name.startswith(TMP_PREFIX) and t.is_dir() and not t.is_symlink() \
                        and now - t.stat().st_mtime >= older_than:
                    shutil.rmtree(t)
                    removed.append(t)
            except OSError:  # vanished meanwhile or not ours to remove: leave it
                continue
    return removed


def _new_version_target(registry: Path, name: str, version) -> tuple[str, Path]:
    """(version, REGISTRY/NAME/VERSION) for a new bundle: the next free version unless one is given
    (never an existing one); the model folder exists and stale temporary folders are removed."""
    version = next_version(registry, name) if version is None else check_version(version)
    target = registry / name / version
    if target.exists():
        raise BundleError(f"bundle {name}:{version} already exists at {target}; versions are never overwritten")
    (registry / name).mkdir(parents=True, exist_ok=True)
    remove_stale_temps(registry, STALE_TMP_SECONDS, name)
    return version, target


def save_bundle(model: GPNARX, registry, name: str, version=None, *, fs: float, units: dict,
                physics: dict | None = None, novelty: dict | None = None, training: dict | None = None,
                extra: dict | None = None, extra_files: dict | None = None,
                attach_dir: Path | None = None) -> Path:
    """Write ``model`` as REGISTRY/NAME/VERSION atomically; returns the bundle folder.

    extra_files: optional {filename: bytes} written next to the manifest; they are checksummed too.
    attach_dir: optional folder copied into the bundle as ``report/`` (human-readable report; not
    needed to load the model, so not checksummed).
    """
    if not hasattr(model, "posterior_"):
        raise BundleError("cannot save an unfitted model")
    registry = Path(registry)
    check_name(name)
    version, target = _new_version_target(registry, name, version)
    tmp = Path(tempfile.mkdtemp(prefix=f"{TMP_PREFIX}{version}-", dir=registry / name))
    try:
        files = {}
        for stem, arr in model_arrays(model).items():
            fn = f"{stem}.npy"
            np.save(tmp / fn, np.ascontiguousarray(arr, dtype=np.float64), allow_pickle=False)
            files[fn] = _sha256(tmp / fn)
        for fn, data in (extra_files or {}).items():
            if "/" in fn or fn.startswith(".") or fn == MANIFEST:
                raise BundleError(f"extra file name {fn!r} is not allowed")
            (tmp / fn).write_bytes(data)
            files[fn] = _sha256(tmp / fn)
        if attach_dir is not None:
            shutil.copytree(attach_dir, tmp / "report")
        manifest = {
            "schema_version": SCHEMA_VERSION,
            "name": name,
            "version": version,
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "lags": {"ny": model.ny, "nu": model.nu},
            "mode": model.posterior_.kind,
            "kernel": model.posterior_.kernel.to_dict(),  # the posterior's (constant cap included)
            "hyperparameters": {**model.kernel_.params, "noise_var": model.noise_var_},
            "noise_var": model.noise_var_,
            "noise_calibration": getattr(model, "noise_calibration_", None),
            "band_discrepancy": getattr(model, "band_discrepancy_", None),
            "training_envelope": getattr(model, "envelope_", None),
            "nlml": None if not np.isfinite(model.nlml_) else model.nlml_,
            "n_train": model.n_train_,
            "estimator": {"include_noise": bool(model.include_noise), "n_inducing": int(model.n_inducing),
                          "max_train_points": model.max_train_points, "selection": model.selection,
                          "seed": int(model.seed), "hyper": model.hyper,
                          "constant_cap": model.constant_cap,
                          "kernel_spec": model.kernel if isinstance(model.kernel, str) else None},
            "fs": float(fs),
            "units": dict(units),
            "physics": dict(physics or {}),
            "novelty": novelty,
            "training": training or {},
            "package_versions": _package_versions(),
            "files": files,
        }
        if extra:
            manifest.update({k: v for k, v in extra.items() if k not in manifest})
        with open(tmp / MANIFEST, "w") as f:
            json.dump(manifest, f, indent=1, allow_nan=False, default=_json_default)
            f.flush()
            os.fsync(f.fileno())
        (tmp / MANIFEST_SUM).write_text(_sha256(tmp / MANIFEST) + "\n")
        os.rename(tmp, target)  # atomic on one filesystem; fails if target appeared meanwhile
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


def derive_bundle(bundle: "Bundle", registry, updates: dict, version=None, name: str | None = None) -> Path:
    """Write a new version of ``bundle`` whose manifest is the old one with ``updates`` applied
    (top-level keys replaced), atomically, without refitting: every array file is copied byte for
    byte after its checksum is verified again, so the GP (lags, scalers, hyperparameters,
    posterior) is the very same. ``created`` is the new write's time and ``derived_from`` names the
    source version. The source's ``report/`` is not copied (it describes the source's training and
    its novelty figures). Returns the new bundle folder; used by ``gpnarx calibrate``.
    """
    registry = Path(registry)
    name = check_name(name or bundle.name)
    protected = {"schema_version", "name", "version", "created", "files", "lags", "kernel", "noise_var", "mode",
                 "estimator", "hyperparameters"}
    bad = sorted(set(updates) & protected)
    if bad:
        raise BundleError(f"a derived bundle keeps the source's model: {', '.join(bad)} cannot be changed")
    version, target = _new_version_target(registry, name, version)
    src = Path(bundle.path)
    tmp = Path(tempfile.mkdtemp(prefix=f"{TMP_PREFIX}{version}-", dir=registry / name))
    try:
        for fn, sha in bundle.manifest["files"].items():
            shutil.copyfile(src / fn, tmp / fn)
            if _sha256(tmp / fn) != sha:
                raise BundleError(f"{src / fn}: sha256 checksum does not match the manifest (file changed)")
        manifest = {**bundle.manifest, **updates, "name": name, "version": version,
                    "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                    "derived_from": {"name": bundle.name, "version": bundle.version,
                                     "created": bundle.manifest.get("created")}}
        manifest.pop("schema_version_written", None)  # the derived manifest is written in today's schema
        with open(tmp / MANIFEST, "w") as f:
            json.dump(manifest, f, indent=1, allow_nan=False, default=_json_default)
            f.flush()
            os.fsync(f.fileno())
        (tmp / MANIFEST_SUM).write_text(_sha256(tmp / MANIFEST) + "\n")
        os.rename(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _migrate_1_to_2(m: dict) -> None:
    """Schema 1 manifests could lack keys that later writers always add; schema 2 holds them all.

    A missing ``estimator.constant_cap`` means the bundle was built without the variance cap
    (docs/numerics.md, safeguard 1): recorded in ``legacy`` so the load can warn."""
    est = m["estimator"]
    legacy = []
    if "constant_cap" not in est:
        est["constant_cap"] = None
        legacy.append("no_constant_cap")
    for key, default in (("n_inducing", 256), ("max_train_points", None), ("selection", "stride"), ("seed", 0),
                         ("include_noise", True), ("hyper", "subset"), ("kernel_spec", None)):
        est.setdefault(key, default)
    for key, default in (("noise_calibration", None), ("training_envelope", None), ("nlml", None), ("n_train", 0),
                         ("physics", {}), ("novelty", None), ("training", {})):
        m.setdefault(key, default)
    m["legacy"] = legacy
    m["schema_version"] = 2


#: schema version -> in-place migration to the next version
MIGRATIONS = {1: _migrate_1_to_2}


def migrate_manifest(manifest: dict) -> dict:
    """Bring a manifest of any supported schema version up to ``SCHEMA_VERSION`` (in place)."""
    v = manifest.get("schema_version")
    if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= SCHEMA_VERSION:
        raise BundleError(f"schema_version {v!r} is not supported (this package reads 1 to {SCHEMA_VERSION})")
    manifest["schema_version_written"] = v
    while manifest["schema_version"] < SCHEMA_VERSION:
        MIGRATIONS[manifest["schema_version"]](manifest)
    manifest.setdefault("legacy", [])
    return manifest


def _read_manifest(path: Path) -> dict:
    mf = path / MANIFEST
    if not mf.is_file():
        raise BundleError(f"{path}: no {MANIFEST}")
    if mf.stat().st_size > MAX_MANIFEST_BYTES:
        raise BundleError(f"{mf}: manifest larger than {MAX_MANIFEST_BYTES} bytes")
    sf = path / MANIFEST_SUM
    if not sf.is_file():
        raise BundleError(f"{sf}: missing (the manifest checksum)")
    if sf.read_text().strip() != _sha256(mf):
        raise BundleError(f"{mf}: sha256 does not match {MANIFEST_SUM} (manifest edited or corrupted)")
    try:
        manifest = json.loads(mf.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BundleError(f"{mf}: not valid JSON ({exc})") from None
    if not isinstance(manifest, dict):
        raise BundleError(f"{mf}: manifest must be a JSON object")
    missing = [k for k in REQUIRED_KEYS if k not in manifest]
    if missing:
        raise BundleError(f"{mf}: missing keys {missing}")
    try:
        return migrate_manifest(manifest)
    except BundleError as exc:
        raise BundleError(f"{mf}: {exc}") from None


def _load_array(path: Path, fn: str, expected_sha: str) -> np.ndarray:
    fp = path / fn
    if not fp.is_file():
        raise BundleError(f"{fp}: array file missing")
    if _sha256(fp) != expected_sha:
        raise BundleError(f"{fp}: sha256 checksum does not match the manifest (file corrupted or changed)")
    try:
        arr = np.load(fp, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise BundleError(f"{fp}: not a readable .npy array ({exc})") from None
    if arr.dtype != np.float64 or not np.all(np.isfinite(arr)):
        raise BundleError(f"{fp}: array must be finite float64")
    return arr


def load_bundle(path) -> Bundle:
    """Load and verify one bundle folder (manifest schema and every checksum)."""
    path = Path(path)
    manifest = _read_manifest(path)
    try:
        check_name(manifest["name"])
        check_version(manifest["version"])
        files = manifest["files"]
        if not isinstance(files, dict):
            raise BundleError("files must be an object")
        for fn in files:
            if not isinstance(fn, str) or "/" in fn or "\\" in fn or fn.startswith("."):
                raise BundleError(f"file name {fn!r} is not allowed")
        arrays = {fn[:-4]: _load_array(path, fn, sha) for fn, sha in files.items() if fn.endswith(".npy")}
        for fn, sha in files.items():
            if not fn.endswith(".npy") and (not (path / fn).is_file() or _sha256(path / fn) != sha):
                raise BundleError(f"{path / fn}: missing or sha256 checksum does not match the manifest")
        ny, nu = int(manifest["lags"]["ny"]), int(manifest["lags"]["nu"])
        est = manifest["estimator"]
        kernel = kernel_from_dict(manifest["kernel"])
        model = GPNARX(ny=ny, nu=nu, kernel=est["kernel_spec"] or kernel, mode=manifest["mode"],
                       n_inducing=int(est["n_inducing"]), max_train_points=est["max_train_points"],
                       selection=est["selection"], seed=int(est["seed"]),
                       include_noise=bool(est["include_noise"]), hyper=est["hyper"],
                       constant_cap=est["constant_cap"])
        model._validate_params()
        model.kernel_ = kernel
        model.theta_ = arrays["theta"]
        model.noise_var_ = float(manifest["noise_var"])
        model.envelope_ = check_envelope(manifest["training_envelope"])  # None: no range checks
        model.noise_calibration_ = manifest["noise_calibration"]  # None: no held-out calibration
        # None: no model-discrepancy term in the band (model.discrepancy); absent in older bundles
        model.band_discrepancy_ = check_discrepancy(manifest.get("band_discrepancy"))
        model.noise_var_ml2_ = float(model.noise_calibration_["noise_var_ml2"]) if model.noise_calibration_ \
            else model.noise_var_
        model.nlml_ = float("nan") if manifest["nlml"] is None else float(manifest["nlml"])
        model.n_train_ = int(manifest["n_train"])
        model.x_scaler_ = Standardizer.from_arrays(arrays["x_mean"], arrays["x_scale"])
        model.y_scaler_ = Standardizer.from_arrays(arrays["y_mean"], arrays["y_scale"])
        post = {k[len("posterior_"):]: v for k, v in arrays.items() if k.startswith("posterior_")}
        if manifest["mode"] == "exact":
            model.posterior_ = ExactPosterior.from_arrays(kernel, model.noise_var_, post)
        elif manifest["mode"] == "sparse":
            model.posterior_ = SparsePosterior.from_arrays(kernel, model.noise_var_, post)
        else:
            raise BundleError(f"mode {manifest['mode']!r} unknown")
        D = ny + nu
        if model.x_scaler_.mean_.shape != (D,) or model.posterior_.X.shape[1] != D:
            raise BundleError(f"array shapes do not match lags ny={ny}, nu={nu}")
        if manifest["mode"] == "sparse" and "posterior_A" in arrays:  # unfactored A (docs/numerics.md, safeguard 2)
            warnings.warn(f"{path}: stores the sparse predictive variance as one matrix A = Kmm^-1 - Sigma^-1, "
                          "whose entries reach 1/jitter; when sigma_y^2 is small, eq. 9's variance then carries "
                          "rounding error larger than itself (and depends on the BLAS thread count). Retrain it "
                          "(gpnarx train CONFIG --registry DIR writes a new version) for the factored form",
                          BundleWarning, stacklevel=2)
        if "no_constant_cap" in manifest["legacy"]:  # no variance cap (docs/numerics.md, safeguard 1)
            shift = kernel.for_posterior(DEFAULT_CONSTANT_CAP).cap_shift()
            if shift > 1e6 * model.noise_var_:  # Bouc-Wen (73 vs 1.1e-2) stays quiet; the stand-in's warns
                warnings.warn(f"{path}: built before the predictive-variance fix; its cubic kernel constant "
                              f"(sigma_p^2 b^3 = {shift + DEFAULT_CONSTANT_CAP:.3g}) makes eq. 9's variance cancel "
                              "below float64 precision, so its 99% bands may carry the noise variance only. Retrain it "
                              "(gpnarx train CONFIG --registry DIR writes a new version)", BundleWarning, stacklevel=2)
    except BundleError as exc:
        msg = str(exc)
        raise BundleError(msg if str(path) in msg else f"{path}: {msg}") from None
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise BundleError(f"{path}: manifest is inconsistent ({type(exc).__name__}: {exc})") from None
    return Bundle(model, manifest, path)


@dataclass
class Registry:
    """A registry folder of bundles. ``scan()`` loads every valid bundle and records refused ones."""

    root: Path
    bundles: dict = field(default_factory=dict)  # name -> {version: Bundle}
    refused: list = field(default_factory=list)  # [{"path":..., "reason":...}]

    def __post_init__(self):
        self.root = Path(self.root)

    def scan(self) -> "Registry":
        bundles: dict = {}
        refused: list = []
        if self.root.is_dir():
            for name_dir in sorted(self.root.iterdir()):
                if not name_dir.is_dir() or name_dir.name.startswith("."):
                    continue
                for vdir in sorted(name_dir.iterdir()):
                    if not vdir.is_dir() or vdir.name.startswith("."):
                        continue  # hidden temporary folders of in-progress writes
                    try:
                        if not NAME_RE.match(name_dir.name) or not VERSION_RE.match(vdir.name):
                            raise BundleError(f"{vdir}: folder name is not NAME/VERSION")
                        b = load_bundle(vdir)
                        if b.name != name_dir.name or b.version != vdir.name:
                            raise BundleError(f"{vdir}: manifest says {b.name}:{b.version}, folder says "
                                              f"{name_dir.name}:{vdir.name}")
                        bundles.setdefault(b.name, {})[b.version] = b
                    except BundleError as exc:
                        refused.append({"path": str(vdir), "reason": str(exc)})
        self.bundles, self.refused = bundles, refused
        return self

    def names(self) -> list[str]:
        return sorted(self.bundles)

    def versions(self, name: str) -> list[str]:
        return sorted(self.bundles.get(name, {}), key=int)

    def get(self, name: str, version: str | None = None) -> Bundle:
        """Bundle by name and version (latest when version is None). Raises KeyError naming what is missing."""
        if name not in self.bundles:
            raise KeyError(f"model {name!r} not found; available: {', '.join(self.names()) or 'none'}")
        if version is None:
            version = self.versions(name)[-1]
        if str(version) not in self.bundles[name]:
            raise KeyError(f"version {version!r} of model {name!r} not found; "
                           f"available: {', '.join(self.versions(name))}")
        return self.bundles[name][str(version)]


def parse_model_ref(ref: str) -> tuple[str, str | None]:
    """'NAME' or 'NAME:VERSION' -> (name, version or None), validated."""
    name, _, version = ref.partition(":")
    check_name(name)
    return name, (check_version(version) if version else None)
