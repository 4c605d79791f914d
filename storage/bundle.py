"""Versioned model bundles: the format, its schema migrations, atomic writes, verified loads.

Layout: ``REGISTRY/NAME/VERSION/`` with ``manifest.json`` and one ``.npy`` file per array.
The manifest holds the schema version, name, version, creation time, lags, kernel and
hyperparameters, fs, units, physical constants, novelty calibration, training metrics, package
versions and the sha256 of every array file. Loading never executes code from a bundle: arrays are
read with ``allow_pickle=False`` and the kernel is rebuilt from a whitelist of types. A bundle
whose manifest or checksums do not verify is refused with a ``BundleError`` naming the file.
Writes are atomic: a bundle is written into a hidden temporary folder and renamed into place, so a
killed run leaves no partial version visible (``Registry.scan`` and ``next_version`` skip hidden
folders). Each temporary folder's name carries its writer (``writer_tag``: a hash of the host name,
the process id and the process's start time), so a leftover ``NAME/.tmp-VERSION-*`` folder whose
writer process is gone from this host is removed at once by ``remove_stale_temps`` (which the
next ``save_bundle`` of the model and every scan of a serving registry run); one of another host,
or without a writer tag, once it is older than ``STALE_TMP_SECONDS`` (one hour, so a write in
progress elsewhere is never touched; a server passes its ``GPNARX_REGISTRY_LEFTOVER_AGE``), or at
once with ``remove_stale_temps(registry, 0)``.
Versions are positive integers, increasing; an existing version is never overwritten.

A registry may also live on object storage behind an fsspec URL (``s3://bucket/prefix``,
``gs://...``; ``storage.remote``). There a version is published by writing its array files (and
report) first and ``manifest.json`` last, so a version whose manifest is absent (in progress, or a
killed write) is not listed; ``manifest.sha256`` goes just before it. The objects of a killed write
(an unpublished version whose newest object is older than a given age: ``stale_unpublished``) are
removed by the next write of that model (``remove_stale_remote``, after ``STALE_TMP_SECONDS``) and
by a serving registry's start and scans (``Registry.remove_leftovers``, after the server's
``GPNARX_REGISTRY_LEFTOVER_AGE``). A live writer uploads its objects one after another, so its newest
object is never older than one file's upload; should its objects be removed all the same, it finds
them gone before writing its manifest and fails instead of publishing a version without them. Readers copy a version's
objects into a local cache, verify them against the manifest's checksums and load from there; an
object rewritten in the store is noticed by its listing (size and ETag) and verified again.

The registry that lists, verifies and serves bundles, and model aliases, are in ``storage.registry``.

What is the method's and what is the file's: a fitted model as plain values (lags, mode, kernel and
hyperparameters, noise variance and its calibration, band discrepancy, training envelope, NLML, the
estimator's settings, and its arrays: scalers, theta, posterior) is the estimator's own description,
``GPNARX.fitted_description()`` / ``fitted_arrays()``, rebuilt by ``GPNARX.from_fitted`` (``gpnarx.model``:
what the values mean). This module is the file format around them: the manifest's other keys, schema
versions and migrations, file names, checksums, atomic publication and verified loading.
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
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gpnarx.checks import is_int
from gpnarx.model.estimator import GPNARX
from gpnarx.model.kernels import DEFAULT_CONSTANT_CAP
from gpnarx.model.mimo import MIMOGPNARX

from .atomicio import plain_modes
from .jsonsafe import json_default
from .remote import RemoteStore, StorageError, as_local

SCHEMA_VERSION = 2  # what save_bundle writes; older manifests are migrated on load (MIGRATIONS)
MANIFEST = "manifest.json"
MANIFEST_SUM = "manifest.sha256"  # sha256 of manifest.json: an edited manifest is refused too
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}\Z")  # \Z: $ would match before a final newline
VERSION_RE = re.compile(r"^[1-9][0-9]{0,8}\Z")
MAX_MANIFEST_BYTES = 4 * 1024 * 1024
TMP_PREFIX = ".tmp-"  # hidden temporary folder of a bundle being written: NAME/.tmp-VERSION-XXXX
STALE_TMP_SECONDS = 3600.0  # a temporary folder untouched this long is a killed write's leftover
_WRITER_RE = re.compile(r"-w([0-9a-f]{8})p(\d+)s(\d+)-")  # writer_tag() inside a temporary folder's name
REQUIRED_KEYS = ("schema_version", "name", "version", "created", "lags", "kernel", "noise_var", "mode",
                 "fs", "units", "files", "estimator")


class BundleError(ValueError):
    """A bundle is missing, malformed or fails its checksums."""


class BundleWarning(UserWarning):
    """A bundle loads and serves, but should be retrained (the message says why)."""


def check_name(name: str, what: str = "model name") -> str:
    if not isinstance(name, str) or not NAME_RE.fullmatch(name) or ".." in name:
        raise BundleError(f"{what} {str(name)[:80]!r} is invalid: use 1-64 letters, digits, '_', '-', '.' "
                          "starting with a letter or digit, without '..'")
    return name


def check_version(version) -> str:
    v = str(version)
    if not VERSION_RE.fullmatch(v):
        raise BundleError(f"version {version!r} is invalid: use a positive integer")
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
    """A loaded bundle: the fitted model plus its manifest (a ``MIMOGPNARX`` for a model with several channels:
    manifest ``model_class`` "mimo", ``channels``)."""

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
                        and (now - t.stat().st_mtime >= older_than or _writer_gone(t)):
                    shutil.rmtree(t)
                    removed.append(t)
            except OSError:  # vanished meanwhile or not ours to remove: leave it
                continue
    return removed


def _process_start(pid: int) -> str | None:
    """The start time of process ``pid`` (clock ticks since boot, Linux ``/proc``), None if it is gone
    or not knowable here."""
    try:
        with open(f"/proc/{int(pid)}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError, ValueError):
        return None


def _host_hash() -> str:
    import socket

    return hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]


def writer_tag() -> str:
    """``w<host hash>p<pid>s<start>``: this process, as a temporary folder's name carries it."""
    return f"w{_host_hash()}p{os.getpid()}s{_process_start(os.getpid()) or 0}"


def _writer_gone(tmp: Path) -> bool:
    """Whether the process that made temporary folder ``tmp`` is known to be gone: its name's writer
    tag is of this host and no process has its id and start time (a folder without one is never judged)."""
    m = _WRITER_RE.search(tmp.name)
    if m is None or m.group(1) != _host_hash() or m.group(3) == "0":
        return False
    return _process_start(int(m.group(2))) != m.group(3)


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
    # the name says who writes it, so a scan removes it at once if this process dies (remove_stale_temps)
    tmp = Path(tempfile.mkdtemp(prefix=f"{TMP_PREFIX}{version}-{writer_tag()}-", dir=local / name))
    try:
        fill(tmp, version)
        # mkdtemp's 0700 (and a copied report's modes) would make the bundle private to its writer: a server
        # running as another user could not read it
        plain_modes(tmp)
        os.rename(tmp, target)  # atomic on one filesystem; fails if target appeared meanwhile
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


def remote_groups(listing: dict) -> dict:
    """{(name, version): {file: info}} of every version prefix in a store ``listing``
    (``RemoteStore.listing``: {relative path: {size, tag, mtime}}), published or not."""
    out: dict = {}
    for rel, info in listing.items():
        parts = rel.split("/")
        if len(parts) >= 3 and NAME_RE.match(parts[0]) and VERSION_RE.match(parts[1]):
            out.setdefault((parts[0], parts[1]), {})["/".join(parts[2:])] = info
    return out


def _remote_versions(store: RemoteStore, name: str) -> dict:
    """{version: {file: info}} of every version prefix of ``name`` in the store, published or not."""
    return {v: files for (n, v), files in remote_groups(store.listing(name)).items() if n == name}


def stale_unpublished(groups: dict, older_than: float, now: float | None = None) -> list[str]:
    """The ``NAME/VERSION/FILE`` objects of the unpublished versions (no manifest) among ``groups``
    (``remote_groups``) whose newest object is at least ``older_than`` seconds old [s]: the leftovers
    of killed writes. A version with an object of unknown time is never judged."""
    import time

    now = time.time() if now is None else now
    out = []
    for (name, version), files in sorted(groups.items()):
        times = [i.get("mtime") for i in files.values()]
        if MANIFEST in files or not times or any(t is None for t in times) or now - max(times) < older_than:
            continue
        out += [f"{name}/{version}/{fn}" for fn in sorted(files)]
    return out


def remove_stale_remote(store: RemoteStore, name: str, older_than: float = STALE_TMP_SECONDS) -> list[str]:
    """Remove the objects of ``name``'s unpublished versions (no manifest) whose newest object is at
    least ``older_than`` seconds old: the leftovers of killed writes. Returns the removed version prefixes."""
    objects = stale_unpublished({(name, v): f for v, f in _remote_versions(store, name).items()}, older_than)
    if objects:
        store.remove(objects)
    return sorted({"/".join(o.split("/")[:2]) for o in objects})


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
            listed = store.listing(prefix)
            if f"{prefix}/{MANIFEST}" in listed:
                clash = True  # another writer published this version meanwhile: leave its objects alone
                raise BundleError(f"bundle {name}:{version} was published by another writer meanwhile at "
                                  f"{store.uri(prefix)}; give concurrent writers distinct versions")
            gone = [rel for rel in uploaded if rel not in listed]
            if gone:  # removed as a killed write's leftovers (an upload slower than their age): never publish
                raise BundleError(f"bundle {name}:{version}: {len(gone)} uploaded object(s) were removed meanwhile "
                                  f"(first {store.uri(gone[0])}), as a killed write's leftovers are; the upload "
                                  f"took longer than the leftover age (GPNARX_REGISTRY_LEFTOVER_AGE); write again")
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


def save_bundle(model: GPNARX | MIMOGPNARX, registry, name: str, version=None, *, fs: float, units: dict,
                physics: dict | None = None, novelty: dict | None = None, training: dict | None = None,
                extra: dict | None = None, extra_files: dict | None = None,
                attach_dir: Path | None = None) -> Path:
    """Write ``model`` as REGISTRY/NAME/VERSION atomically; returns the bundle folder (for an
    object-store registry URL, a ``BundleURI``: the version's URL, whose ``.name`` is the version).

    extra_files: optional {filename: bytes} written next to the manifest; they are checksummed too.
    attach_dir: optional folder copied into the bundle as ``report/`` (human-readable report; not
    needed to load the model, so not checksummed).
    """
    if not (hasattr(model, "posterior_") or hasattr(model, "outputs_")):  # GPNARX, MIMOGPNARX
        raise BundleError("cannot save an unfitted model")
    check_name(name)
    for fn in extra_files or {}:
        if "/" in fn or fn.startswith(".") or fn in (MANIFEST, MANIFEST_SUM):
            raise BundleError(f"extra file name {fn!r} is not allowed")

    def fill(tmp: Path, version: str) -> None:
        files = {}
        for stem, arr in model.fitted_arrays().items():  # one .npy file per array, named by its stem
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
            **model.fitted_description(),  # lags, mode, kernel, ... estimator: the method's description
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
    if not is_int(v, 1, SCHEMA_VERSION):
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
        if manifest.get("model_class") == "mimo":  # several channels (model.mimo): its own shape checks
            return Bundle(MIMOGPNARX.from_fitted(manifest, arrays), manifest, path)
        model = GPNARX.from_fitted(manifest, arrays)  # the manifest's keys are the fitted description's
        kernel, ny, nu = model.kernel_, model.ny, model.nu
        D = ny + nu
        if model.x_scaler_.mean_.shape != (D,) or model.posterior_.points.shape[1] != D:
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
