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

A registry may also live on object storage behind an fsspec URL (``s3://bucket/prefix``,
``gs://...``; ``model.storage``). There a version is published by writing its array files (and
report) first and ``manifest.json`` last, so a version whose manifest is absent (in progress, or a
killed write) is not listed; ``manifest.sha256`` goes just before it. Readers copy a version's
objects into a local cache, verify them against the manifest's checksums and load from there; an
object rewritten in the store is noticed by its listing (size and ETag) and verified again.

Aliases: ``NAME/aliases.json`` (``{"aliases": {"production": "3"}}``), written in one atomic
write (local: temporary file and rename; object store: one PUT); ``latest`` is implicit (the newest
listed version). ``NAME:ALIAS`` is accepted wherever ``NAME:VERSION`` is (``parse_model_ref``).

``Registry(root, lazy=True)`` verifies every version when it scans but builds a model in memory
only on first use, keeping at most ``max_loaded`` built (least recently used dropped first);
``rescan()`` returns a new registry that reuses what did not change (same files, same listing).
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import re
import shutil
import tempfile
import threading
import uuid
import warnings
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomicio import write_atomic
from .discrepancy import check_discrepancy
from .envelope import check_envelope
from .estimator import GPNARX
from .gp import ExactPosterior, SparsePosterior
from .jsonsafe import json_default
from .kernels import DEFAULT_CONSTANT_CAP, kernel_from_dict
from .scaling import Standardizer
from .storage import RemoteStore, StorageError, as_local, cache_dir_for

SCHEMA_VERSION = 2  # what save_bundle writes; older manifests are migrated on load (MIGRATIONS)
MANIFEST = "manifest.json"
MANIFEST_SUM = "manifest.sha256"  # sha256 of manifest.json: an edited manifest is refused too
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
VERSION_RE = re.compile(r"^[1-9][0-9]{0,8}$")
MAX_MANIFEST_BYTES = 4 * 1024 * 1024
TMP_PREFIX = ".tmp-"  # hidden temporary folder of a bundle being written: NAME/.tmp-VERSION-XXXX
STALE_TMP_SECONDS = 3600.0  # a temporary folder untouched this long is a killed write's leftover
ALIASES = "aliases.json"  # NAME/aliases.json: {"aliases": {ALIAS: VERSION}}
ALIAS_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,31}$")
IMPLICIT_ALIASES = ("latest",)  # the newest listed version; never written
FINGERPRINT = ".listing.json"  # in a cached remote version: the store listing it was copied from
DEFAULT_MAX_LOADED = 8  # built bundles kept in memory by a lazy registry (the service's GPNARX_MAX_LOADED)
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


def check_alias(alias, what: str = "alias") -> str:
    a = str(alias)
    if not ALIAS_RE.match(a):
        raise BundleError(f"{what} {alias!r} is invalid: use 1-32 letters, digits, '_', '-' starting with a letter")
    return a


def check_version_ref(ref) -> str:
    """A version (positive integer) or an alias (``production``, ``latest``, ...), validated."""
    v = str(ref)
    if v[:1].isdigit() or not v:
        return check_version(v)
    if not ALIAS_RE.match(v):
        raise BundleError(f"version {ref!r} is invalid: use a positive integer or an alias (1-32 letters, digits, "
                          "'_', '-' starting with a letter, e.g. production or latest)")
    return v


class BundleURI(str):
    """Where a bundle was written on object storage (``s3://bucket/prefix/NAME/VERSION``); like a Path,
    ``.name`` is its last part (the version)."""

    @property
    def name(self) -> str:
        return self.rstrip("/").rsplit("/", 1)[-1]


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


def default_method(manifest: dict, operation: str = "predict") -> str:
    """The propagation ('mc' or 'linear') an answer of ``operation`` uses when the request names none.

    novelty: the one the threshold was calibrated with (``novelty.mc_paths`` 0: linearised), so a
    score is compared with scores of its own kind; predict and loops: the trained config's
    ``[predict] method`` (manifest ``predict.method``; 'mc', the paper's, for bundles without it).
    """
    nov = manifest.get("novelty")
    if operation == "novelty" and isinstance(nov, dict) and nov.get("mc_paths") is not None:
        return "linear" if int(nov["mc_paths"]) == 0 else "mc"
    pred = manifest.get("predict")
    method = pred.get("method") if isinstance(pred, dict) else None
    return method if method in ("mc", "linear") else "mc"


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

    def default_method(self, operation: str = "predict") -> str:
        """The propagation an answer uses when the request names none (``default_method``)."""
        return default_method(self.manifest, operation)


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


def _write_manifest(folder: Path, manifest: dict) -> None:
    with open(folder / MANIFEST, "w") as f:
        json.dump(manifest, f, indent=1, allow_nan=False, default=json_default)
        f.flush()
        os.fsync(f.fileno())
    (folder / MANIFEST_SUM).write_text(_sha256(folder / MANIFEST) + "\n")


def _write_new_version(registry, name: str, version, fill):
    """Write a new version with ``fill(folder, version)`` (which writes every file, manifest last)
    into a temporary folder, then publish it: a local registry renames the folder into place; an
    object store gets the files uploaded, ``manifest.sha256`` and ``manifest.json`` last."""
    local = as_local(registry)
    if local is None:
        store = registry if isinstance(registry, RemoteStore) else RemoteStore(str(registry))
        return _publish_remote(store, name, version, fill)
    version, target = _new_version_target(local, name, version)
    tmp = Path(tempfile.mkdtemp(prefix=f"{TMP_PREFIX}{version}-", dir=local / name))
    try:
        fill(tmp, version)
        os.rename(tmp, target)  # atomic on one filesystem; fails if target appeared meanwhile
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


def _remote_versions(store: RemoteStore, name: str) -> dict:
    """{version: {file: info}} of every version prefix of ``name`` in the store, published or not."""
    out: dict = {}
    for rel, info in store.listing(name).items():
        parts = rel.split("/")
        if len(parts) >= 3 and parts[0] == name and VERSION_RE.match(parts[1]):
            out.setdefault(parts[1], {})["/".join(parts[2:])] = info
    return out


def remove_stale_remote(store: RemoteStore, name: str, older_than: float = STALE_TMP_SECONDS) -> list[str]:
    """Remove the objects of unpublished versions (no manifest) whose newest object is at least
    ``older_than`` seconds old: the leftovers of killed writes. Returns the removed version prefixes."""
    import time

    removed = []
    for version, files in _remote_versions(store, name).items():
        times = [i.get("mtime") for i in files.values()]
        if MANIFEST in files or not times or any(t is None for t in times) or time.time() - max(times) < older_than:
            continue
        store.remove([f"{name}/{version}/{fn}" for fn in files])
        removed.append(f"{name}/{version}")
    return removed


def _publish_remote(store: RemoteStore, name: str, version, fill) -> BundleURI:
    remove_stale_remote(store, name)
    present = _remote_versions(store, name)
    if version is None:  # after every prefix in use, published or still being written
        version = str(max((int(v) for v in present), default=0) + 1)
    else:
        version = check_version(version)
        if version in present:
            raise BundleError(f"bundle {name}:{version} already exists at {store.uri(f'{name}/{version}')}; "
                              "versions are never overwritten")
    prefix = f"{name}/{version}"
    with tempfile.TemporaryDirectory(prefix="gpnarx-publish-") as tmp:
        tmp = Path(tmp)
        fill(tmp, version)
        files = sorted(p for p in tmp.rglob("*") if p.is_file() and p.name not in (MANIFEST, MANIFEST_SUM))
        uploaded, clash = [], False
        try:
            for p in files:
                rel = f"{prefix}/{p.relative_to(tmp).as_posix()}"
                store.put_file(p, rel)
                uploaded.append(rel)
            if f"{prefix}/{MANIFEST}" in store.listing(prefix):
                clash = True  # another writer published this version meanwhile: leave its objects alone
                raise BundleError(f"bundle {name}:{version} was published by another writer meanwhile at "
                                  f"{store.uri(prefix)}; give concurrent writers distinct versions")
            store.put_file(tmp / MANIFEST_SUM, f"{prefix}/{MANIFEST_SUM}")
            uploaded.append(f"{prefix}/{MANIFEST_SUM}")
            store.put_file(tmp / MANIFEST, f"{prefix}/{MANIFEST}")  # last: the version is listed from now on
        except BaseException:
            if not clash:
                try:
                    store.remove(uploaded)
                except StorageError:  # the leftovers stay unlisted and are removed as stale later
                    pass
            raise
    return BundleURI(store.uri(prefix))


def save_bundle(model: GPNARX, registry, name: str, version=None, *, fs: float, units: dict,
                physics: dict | None = None, novelty: dict | None = None, training: dict | None = None,
                extra: dict | None = None, extra_files: dict | None = None,
                attach_dir: Path | None = None) -> Path:
    """Write ``model`` as REGISTRY/NAME/VERSION atomically; returns the bundle folder (for an
    object-store registry URL, a ``BundleURI``: the version's URL, whose ``.name`` is the version).

    extra_files: optional {filename: bytes} written next to the manifest; they are checksummed too.
    attach_dir: optional folder copied into the bundle as ``report/`` (human-readable report; not
    needed to load the model, so not checksummed).
    """
    if not hasattr(model, "posterior_"):
        raise BundleError("cannot save an unfitted model")
    check_name(name)
    for fn in extra_files or {}:
        if "/" in fn or fn.startswith(".") or fn in (MANIFEST, MANIFEST_SUM):
            raise BundleError(f"extra file name {fn!r} is not allowed")

    def fill(tmp: Path, version: str) -> None:
        files = {}
        for stem, arr in model_arrays(model).items():
            fn = f"{stem}.npy"
            np.save(tmp / fn, np.ascontiguousarray(arr, dtype=np.float64), allow_pickle=False)
            files[fn] = _sha256(tmp / fn)
        for fn, data in (extra_files or {}).items():
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
        _write_manifest(tmp, manifest)

    return _write_new_version(registry, name, version, fill)


def derive_bundle(bundle: "Bundle", registry, updates: dict, version=None, name: str | None = None) -> Path:
    """Write a new version of ``bundle`` whose manifest is the old one with ``updates`` applied
    (top-level keys replaced), atomically, without refitting: every array file is copied byte for
    byte after its checksum is verified again, so the GP (lags, scalers, hyperparameters,
    posterior) is the very same. ``created`` is the new write's time and ``derived_from`` names the
    source version. The source's ``report/`` is not copied (it describes the source's training and
    its novelty figures). Returns the new bundle folder (a ``BundleURI`` on object storage); used by
    ``gpnarx calibrate``.
    """
    name = check_name(name or bundle.name)
    protected = {"schema_version", "name", "version", "created", "files", "lags", "kernel", "noise_var", "mode",
                 "estimator", "hyperparameters"}
    bad = sorted(set(updates) & protected)
    if bad:
        raise BundleError(f"a derived bundle keeps the source's model: {', '.join(bad)} cannot be changed")
    src = Path(bundle.path)

    def fill(tmp: Path, version: str) -> None:
        for fn, sha in bundle.manifest["files"].items():
            shutil.copyfile(src / fn, tmp / fn)
            if _sha256(tmp / fn) != sha:
                raise BundleError(f"{src / fn}: sha256 checksum does not match the manifest (file changed)")
        manifest = {**bundle.manifest, **updates, "name": name, "version": version,
                    "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                    "derived_from": {"name": bundle.name, "version": bundle.version,
                                     "created": bundle.manifest.get("created")}}
        manifest.pop("schema_version_written", None)  # the derived manifest is written in today's schema
        _write_manifest(tmp, manifest)

    return _write_new_version(registry, name, version, fill)


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


def _check_files(files) -> dict:
    if not isinstance(files, dict):
        raise BundleError("files must be an object")
    for fn in files:
        if not isinstance(fn, str) or "/" in fn or "\\" in fn or fn.startswith("."):
            raise BundleError(f"file name {fn!r} is not allowed")
    return files


def verify_bundle(path) -> dict:
    """Check one bundle folder without building its model: the manifest (its checksum, schema,
    name and version) and the sha256 of every file it lists. Returns the manifest; a
    ``BundleError`` naming the file otherwise."""
    path = Path(path)
    manifest = _read_manifest(path)
    try:
        check_name(manifest["name"])
        check_version(manifest["version"])
        for fn, sha in _check_files(manifest["files"]).items():
            fp = path / fn
            if not fp.is_file():
                raise BundleError(f"{fp}: {'array file' if fn.endswith('.npy') else 'file'} missing")
            if _sha256(fp) != sha:
                raise BundleError(f"{fp}: sha256 checksum does not match the manifest (file corrupted or changed)")
    except BundleError as exc:
        msg = str(exc)
        raise BundleError(msg if str(path) in msg else f"{path}: {msg}") from None
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise BundleError(f"{path}: manifest is inconsistent ({type(exc).__name__}: {exc})") from None
    return manifest


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
        model._check_params()
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
class BundleRef:
    """A verified bundle whose model is built on first use (``Registry(lazy=True)``): its manifest
    and files passed their checksums when the registry was scanned."""

    name: str
    version: str
    path: Path
    manifest: dict
    fingerprint: tuple

    @property
    def fs(self) -> float:
        return float(self.manifest["fs"])

    def default_method(self, operation: str = "predict") -> str:
        """The propagation an answer uses when the request names none (``default_method``)."""
        return default_method(self.manifest, operation)


class _Loaded:
    """Built bundles by (name, version, fingerprint), least recently used dropped beyond ``limit``
    (0: no limit); one build per key at a time, shared by a registry and its rescans."""

    def __init__(self, limit: int):
        self.limit = int(limit)
        self.items: OrderedDict = OrderedDict()
        self.lock = threading.Lock()
        self.building: dict = {}

    def peek(self, key) -> bool:
        with self.lock:
            return key in self.items

    def get(self, key, build):
        with self.lock:
            if key in self.items:
                self.items.move_to_end(key)
                return self.items[key]
            key_lock = self.building.setdefault(key, threading.Lock())
        with key_lock:
            try:
                with self.lock:
                    if key in self.items:
                        self.items.move_to_end(key)
                        return self.items[key]
                bundle = build()
                with self.lock:
                    for other in [k for k in self.items if k[:2] == key[:2]]:  # a rewritten version's old build
                        del self.items[other]
                    self.items[key] = bundle
                    while self.limit and len(self.items) > self.limit:
                        self.items.popitem(last=False)
                return bundle
            finally:
                with self.lock:
                    self.building.pop(key, None)

    def __len__(self) -> int:
        with self.lock:
            return len(self.items)


def _parse_aliases(raw: bytes, where: str) -> dict:
    try:
        data = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BundleError(f"{where}: not valid JSON ({exc})") from None
    aliases = data.get("aliases") if isinstance(data, dict) else None
    if not isinstance(aliases, dict):
        raise BundleError(f"{where}: must be a JSON object {{\"aliases\": {{ALIAS: VERSION}}}}")
    out = {}
    for alias, version in aliases.items():
        try:
            check_alias(alias)
            if alias in IMPLICIT_ALIASES:
                raise BundleError(f"alias {alias!r} is implicit and cannot be set")
            out[alias] = check_version(version)
        except BundleError as exc:
            raise BundleError(f"{where}: {exc}") from None
    return out


def _registry_location(registry):
    """(local folder, None) or (None, RemoteStore) of a registry given as a path, URL or store."""
    if isinstance(registry, RemoteStore):
        return None, registry
    local = as_local(registry)
    return (local, None) if local is not None else (None, RemoteStore(str(registry)))


def read_aliases(registry, name: str) -> dict:
    """The aliases set for model ``name`` ({} when none), as written in REGISTRY/NAME/aliases.json."""
    check_name(name)
    local, store = _registry_location(registry)
    if local is not None:
        f = local / name / ALIASES
        return _parse_aliases(f.read_bytes(), str(f)) if f.is_file() else {}
    rel = f"{name}/{ALIASES}"
    if rel not in store.listing(rel):
        return {}
    return _parse_aliases(store.read_bytes(rel), store.uri(rel))


def write_aliases(registry, name: str, aliases: dict) -> None:
    """Replace model ``name``'s aliases in one atomic write (local: temporary file and rename;
    object store: one PUT, so a reader sees the old or the new set, never a mix)."""
    check_name(name)
    clean = {}
    for alias, version in sorted(aliases.items()):
        check_alias(alias)
        if alias in IMPLICIT_ALIASES:
            raise BundleError(f"alias {alias!r} is implicit (the newest version) and cannot be set")
        clean[alias] = check_version(version)
    data = json.dumps({"aliases": clean, "updated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")},
                      indent=1).encode() + b"\n"
    local, store = _registry_location(registry)
    if local is not None:
        if not (local / name).is_dir():
            raise BundleError(f"model {name!r} not found in {local}")
        write_atomic(local / name / ALIASES, data)
    else:
        store.put_bytes(f"{name}/{ALIASES}", data)


class Registry:
    """A registry of bundles: a local folder or an fsspec URL (``s3://bucket/prefix``, ...).

    ``scan()`` verifies every version and records refused ones. By default (``lazy=False``) it also
    builds every model, as ``bundles[name][version]`` (a ``Bundle``); with ``lazy=True`` the entries
    are ``BundleRef``s and ``get()`` builds a model on first use, keeping at most ``max_loaded``
    built. ``aliases[name]`` holds the aliases set for a model. ``rescan()`` is a new registry over
    the same location that reuses every version whose files (local: names, sizes and modification
    times; object store: names, sizes and ETags) did not change, and the built models.
    """

    def __init__(self, root, *, lazy: bool = False, max_loaded: int = DEFAULT_MAX_LOADED,
                 storage_options: dict | None = None):
        if isinstance(root, RemoteStore):
            local, self.store = None, root
        else:
            local = as_local(root)
            self.store = None if local is not None else RemoteStore(str(root), storage_options)
        self.root = local if local is not None else self.store.url
        self.lazy = bool(lazy)
        self.bundles: dict = {}  # name -> {version: Bundle | BundleRef}
        self.refused: list = []  # [{"path":..., "reason":...}]
        self.aliases: dict = {}  # name -> {alias: version} (set ones; "latest" is implicit)
        self._seen: dict = {}  # (name, version) -> (fingerprint, entry or None, reason or None)
        self._alias_seen: dict = {}  # name -> (fingerprint, aliases or None, reason or None)
        self._loaded = _Loaded(max_loaded)
        self._only: str | None = None
        self._lock = threading.Lock()

    @property
    def remote(self) -> bool:
        return self.store is not None

    def _child(self) -> "Registry":
        new = object.__new__(Registry)
        new.store, new.root, new.lazy, new._loaded, new._only = self.store, self.root, self.lazy, self._loaded, \
            self._only
        new.bundles, new.refused, new.aliases, new._seen, new._alias_seen = {}, [], {}, {}, {}
        new._lock = threading.Lock()
        return new

    def scan(self, only: str | None = None) -> "Registry":
        """Verify every version (of model ``only`` alone when given) and list the valid ones."""
        self._only = check_name(only) if only is not None else None
        return self._scan({}, {})

    def rescan(self) -> "Registry":
        """A new registry over the same location, scanned again; unchanged versions are not re-verified."""
        return self._child()._scan(self._seen, self._alias_seen)

    # ---------------------------------------------------------------- scanning
    def _display(self, name: str, version: str | None = None) -> str:
        parts = [name] + ([version] if version is not None else [])
        return self.store.uri("/".join(parts)) if self.remote else str(Path(self.root, *parts))

    def _scan(self, seen: dict, alias_seen: dict) -> "Registry":
        versions, alias_files = self._list_remote() if self.remote else self._list_local()
        bundles: dict = {}
        refused: list = []
        for (name, version), fingerprint in sorted(versions.items()):
            key = (name, version)
            old = seen.get(key)
            if fingerprint is not None and old is not None and old[0] == fingerprint:
                entry, reason = old[1], old[2]
            else:
                entry, reason = self._verify(name, version, fingerprint)
            self._seen[key] = (fingerprint, entry, reason)
            if entry is not None:
                bundles.setdefault(name, {})[version] = entry
            else:
                refused.append({"path": self._display(name, version), "reason": reason})
        aliases: dict = {}
        for name, fingerprint in sorted(alias_files.items()):
            old = alias_seen.get(name)
            if fingerprint is not None and old is not None and old[0] == fingerprint:
                got, reason = old[1], old[2]
            else:
                try:
                    got, reason = read_aliases(self.store or self.root, name), None
                except (BundleError, StorageError) as exc:
                    got, reason = None, str(exc)
            self._alias_seen[name] = (fingerprint, got, reason)
            if got:
                aliases[name] = got
            elif reason:
                refused.append({"path": f"{self._display(name)}/{ALIASES}", "reason": reason})
        self.bundles, self.refused, self.aliases = bundles, refused, aliases
        return self

    def _list_local(self) -> tuple[dict, dict]:
        """{(name, version): fingerprint} of every version folder, {name: fingerprint} of alias files."""
        versions, alias_files = {}, {}
        root = self.root
        if not root.is_dir():
            return versions, alias_files
        name_dirs = [root / self._only] if self._only else sorted(root.iterdir())
        for name_dir in name_dirs:
            if not name_dir.is_dir() or name_dir.name.startswith("."):
                continue
            if (name_dir / ALIASES).is_file():
                alias_files[name_dir.name] = None  # small: read at every scan
            for vdir in sorted(name_dir.iterdir()):
                if not vdir.is_dir() or vdir.name.startswith("."):
                    continue  # hidden temporary folders of in-progress writes
                try:
                    fingerprint = tuple(sorted((f.name, st.st_size, st.st_mtime_ns) for f in vdir.iterdir()
                                               if f.is_file() and (st := f.stat())))
                except OSError:
                    fingerprint = None  # vanishing meanwhile: verify it now
                versions[(name_dir.name, vdir.name)] = fingerprint
        return versions, alias_files

    def _list_remote(self) -> tuple[dict, dict]:
        groups: dict = {}
        alias_files: dict = {}
        for rel, info in self.store.listing(self._only or "").items():
            parts = rel.split("/")
            if len(parts) == 2 and parts[1] == ALIASES:
                alias_files[parts[0]] = (info["size"], info["tag"])
            if len(parts) < 3 or parts[0].startswith(".") or parts[1].startswith("."):
                continue
            groups.setdefault((parts[0], parts[1]), {})["/".join(parts[2:])] = info
        versions = {}
        for key, files in groups.items():
            if MANIFEST not in files:
                continue  # not published yet (or a killed write): not listed
            versions[key] = tuple(sorted((fn, i["size"], i["tag"]) for fn, i in files.items()))
        return versions, alias_files

    def _verify(self, name: str, version: str, fingerprint) -> tuple:
        """(entry, None) for a valid version, (None, reason) for a refused one."""
        where = self._display(name, version)

        def check(path: Path):
            if self.lazy:
                manifest = verify_bundle(path)
                entry, got = BundleRef(name, version, path, manifest, fingerprint), (manifest["name"],
                                                                                      str(manifest["version"]))
            else:
                entry = load_bundle(path)
                got = (entry.name, entry.version)
            if got != (name, version):
                raise BundleError(f"{where}: manifest says {got[0]}:{got[1]}, folder says {name}:{version}")
            return entry

        path = None
        try:
            if not NAME_RE.match(name) or not VERSION_RE.match(version):
                raise BundleError(f"{where}: folder name is not NAME/VERSION")
            if not self.remote:
                return check(Path(where)), None
            path, fresh = self._fetch(name, version, fingerprint)
            try:
                return check(path), None
            except BundleError:
                if fresh:
                    raise
                path, _ = self._fetch(name, version, fingerprint, force=True)  # a damaged cached copy
                return check(path), None
        except (BundleError, StorageError) as exc:
            msg = str(exc)
            if path is not None:
                msg = msg.replace(str(path), where)
            return None, msg

    def _fetch(self, name: str, version: str, fingerprint: tuple, force: bool = False) -> tuple[Path, bool]:
        """(local copy of a remote version, whether it was copied now). Copies are immutable, one
        folder per store listing (``CACHE/NAME/VERSION/KEY``, KEY a hash of the listing), so readers
        sharing a cache folder never see one change under them: a copy another process placed for
        the same listing is used as it is. Copies of older listings are removed once an hour old.
        The caller verifies the copy; ``force`` replaces a damaged one."""
        base = cache_dir_for(self.store.url) / name / version
        stamp = json.dumps([list(f) for f in fingerprint], default=str)
        target = base / hashlib.sha256(stamp.encode()).hexdigest()[:16]
        if not force and self._stamp(target) == stamp:
            return target, False
        base.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=TMP_PREFIX, dir=base))
        try:
            for fn, size, _tag in fingerprint:
                if ".." in fn.split("/") or fn.startswith("/") or fn == FINGERPRINT:
                    continue
                if fn == MANIFEST and size > MAX_MANIFEST_BYTES:
                    raise BundleError(f"{self._display(name, version)}/{MANIFEST}: manifest larger than "
                                      f"{MAX_MANIFEST_BYTES} bytes")
                dest = tmp / fn
                dest.parent.mkdir(parents=True, exist_ok=True)
                self.store.download(f"{name}/{version}/{fn}", dest)
            (tmp / FINGERPRINT).write_text(stamp)
            if force and target.exists():  # a damaged copy: moved aside, replaced
                aside = base / f"{TMP_PREFIX}damaged-{uuid.uuid4().hex[:8]}"
                try:
                    os.rename(target, aside)
                    shutil.rmtree(aside, ignore_errors=True)
                except OSError:
                    pass
            try:
                os.rename(tmp, target)
            except OSError:
                if self._stamp(target) != stamp:
                    raise StorageError(f"{target}: cannot place the copy of {self._display(name, version)}") from None
                shutil.rmtree(tmp, ignore_errors=True)  # another process placed the same copy meanwhile
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        self._remove_old_copies(base, keep=target)
        return target, True

    @staticmethod
    def _remove_old_copies(base: Path, keep: Path) -> None:
        import time

        now = time.time()
        for d in base.iterdir():
            try:
                if d != keep and d.is_dir() and now - d.stat().st_mtime >= STALE_TMP_SECONDS:
                    shutil.rmtree(d, ignore_errors=True)
            except OSError:
                continue

    @staticmethod
    def _stamp(copy: Path) -> str | None:
        try:
            return (copy / FINGERPRINT).read_text()
        except OSError:
            return None

    # ---------------------------------------------------------------- lookups
    def names(self) -> list[str]:
        return sorted(self.bundles)

    def versions(self, name: str) -> list[str]:
        return sorted(self.bundles.get(name, {}), key=int)

    def aliases_of(self, name: str) -> dict:
        """{alias: version} of a listed model: ``latest`` and the set aliases whose version is listed."""
        if name not in self.bundles:
            return {}
        out = {"latest": self.versions(name)[-1]}
        out.update({a: v for a, v in sorted(self.aliases.get(name, {}).items()) if v in self.bundles[name]})
        return out

    def resolve(self, name: str, version: str | None = None) -> str:
        """The version a reference names: None or ``latest`` -> the newest, an alias -> its version.
        Raises KeyError naming what is missing."""
        if name not in self.bundles:
            if self._only:
                raise KeyError(f"model {name!r} not found in {self.root}")
            raise KeyError(f"model {name!r} not found; available: {', '.join(self.names()) or 'none'}")
        version = None if version is None else str(version)
        if version is None or version == "latest":
            return self.versions(name)[-1]
        if VERSION_RE.match(version):
            if version not in self.bundles[name]:
                raise KeyError(f"version {version!r} of model {name!r} not found"
                               f"{self._refusal(name, version)}; available: {', '.join(self.versions(name))}")
            return version
        target = self.aliases.get(name, {}).get(version)
        if target is None:
            raise KeyError(f"alias {version!r} of model {name!r} not found; aliases: "
                           f"{', '.join(self.aliases_of(name))}")
        if target not in self.bundles[name]:
            raise KeyError(f"alias {version!r} of model {name!r} names version {target}, which is not available"
                           f"{self._refusal(name, target)}; available: {', '.join(self.versions(name))}")
        return target

    def _refusal(self, name: str, version: str) -> str:
        where = self._display(name, version)
        for r in self.refused:
            if r["path"] == where:
                return f" (refused: {r['reason']})"
        return ""

    def entry(self, name: str, version: str | None = None):
        """The ``Bundle`` or ``BundleRef`` a reference names, without building a model."""
        version = self.resolve(name, version)  # first: it names what is missing
        return self.bundles[name][version]

    def is_built(self, name: str, version: str | None = None) -> bool:
        try:
            e = self.entry(name, version)
        except KeyError:
            return True  # nothing to build: the lookup fails at once
        return isinstance(e, Bundle) or self._loaded.peek((e.name, e.version, e.fingerprint))

    def loaded_count(self) -> int:
        """Models built in memory (every listed one for a registry that is not lazy)."""
        return len(self._loaded) if self.lazy else sum(len(v) for v in self.bundles.values())

    def get(self, name: str, version: str | None = None) -> Bundle:
        """Bundle by name and version or alias (latest when None), built if needed. Raises KeyError
        naming what is missing; a lazy bundle whose files no longer verify is refused from then on."""
        e = self.entry(name, version)
        if isinstance(e, Bundle):
            return e
        try:
            return self._loaded.get((e.name, e.version, e.fingerprint), lambda: load_bundle(e.path))
        except BundleError as exc:
            reason = str(exc)
            if self.remote:
                reason = reason.replace(str(e.path), self._display(e.name, e.version))
            with self._lock:  # new containers swapped in: readers iterating the old ones are not disturbed
                if e.version in self.bundles.get(e.name, {}):
                    left = {v: b for v, b in self.bundles[e.name].items() if v != e.version}
                    self.bundles = {n: (left if n == e.name else vs) for n, vs in self.bundles.items()
                                    if n != e.name or left}
                    self.refused = [*self.refused, {"path": self._display(e.name, e.version), "reason": reason}]
                    self._seen[(e.name, e.version)] = (e.fingerprint, None, reason)
            raise KeyError(f"version {e.version!r} of model {e.name!r} was refused: {reason}") from None


def parse_model_ref(ref: str) -> tuple[str, str | None]:
    """'NAME', 'NAME:VERSION' or 'NAME:ALIAS' (``production``, ``latest``, ...) -> (name, version or
    alias or None), validated."""
    name, _, version = ref.partition(":")
    check_name(name)
    return name, (check_version_ref(version) if version else None)
