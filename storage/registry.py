"""The registry: versioned bundles by model name, their aliases, and models built on first use.

A registry is a local folder or an fsspec URL (``s3://bucket/prefix``, ``gs://...``) holding
``NAME/VERSION/`` bundles (``storage.bundle``). ``Registry.scan`` verifies every version and records
the refused ones; a refused version never stops the others from serving.

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
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

from .atomicio import plain_modes, write_atomic
from .bundle import (
    MANIFEST,
    MAX_MANIFEST_BYTES,
    NAME_RE,
    STALE_TMP_SECONDS,
    TMP_PREFIX,
    VERSION_RE,
    Bundle,
    BundleError,
    check_name,
    check_version,
    default_method,
    load_bundle,
    remove_stale_temps,
    stale_unpublished,
    verify_bundle,
)
from .remote import RemoteStore, StorageError, as_local, cache_dir_for

ALIASES = "aliases.json"  # NAME/aliases.json: {"aliases": {ALIAS: VERSION}}
ALIAS_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,31}\Z")  # \Z: $ would match before a final newline
IMPLICIT_ALIASES = ("latest",)  # the newest listed version; never written
FINGERPRINT = ".listing.json"  # in a cached remote version: the store listing it was copied from
DEFAULT_MAX_LOADED = 8  # built bundles kept in memory by a lazy registry (the service's GPNARX_MAX_LOADED)


def unreadable(where: str, exc: OSError) -> str:
    """Why ``where`` (a bundle, a model folder, an alias file) is refused when reading it raised ``exc``."""
    name = os.path.basename(exc.filename) if isinstance(exc.filename, str) else ""
    uid = f" (uid {os.getuid()})" if hasattr(os, "getuid") else ""
    return (f"{where}: cannot be read: {exc.strerror or type(exc).__name__}{f' ({name})' if name else ''}; its "
            f"folders and files must be readable by the user this process runs as{uid}")


def check_alias(alias, what: str = "alias") -> str:
    a = str(alias)
    if not ALIAS_RE.fullmatch(a):
        raise BundleError(f"{what} {alias!r} is invalid: use 1-32 letters, digits, '_', '-' starting with a letter")
    return a


def check_version_ref(ref) -> str:
    """A version (positive integer) or an alias (``production``, ``latest``, ...), validated."""
    v = str(ref)
    if v[:1].isdigit() or not v:
        return check_version(v)
    if not ALIAS_RE.fullmatch(v):
        raise BundleError(f"version {ref!r} is invalid: use a positive integer or an alias (1-32 letters, digits, "
                          "'_', '-' starting with a letter, e.g. production or latest)")
    return v



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
        self._unlisted: dict = {}  # model folders the last local scan could not list: name -> reason
        self._lock = threading.Lock()
        self.unpublished: dict = {}  # object store: {(name, version): {file: info}} listed without a manifest

    @property
    def remote(self) -> bool:
        return self.store is not None

    def _child(self) -> "Registry":
        new = object.__new__(Registry)
        new.store, new.root, new.lazy, new._loaded, new._only = self.store, self.root, self.lazy, self._loaded, \
            self._only
        new.bundles, new.refused, new.aliases, new._seen, new._alias_seen = {}, [], {}, {}, {}
        new._lock = threading.Lock()
        new.unpublished, new._unlisted = {}, {}
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
        for name, reason in sorted(self._unlisted.items()):  # model folders this process may not list
            refused.append({"path": self._display(name), "reason": reason})
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
                except OSError as exc:  # another user's private file
                    got, reason = None, unreadable(f"{self._display(name)}/{ALIASES}", exc)
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
        self._unlisted = {}
        root = self.root
        try:
            if not root.is_dir():
                return versions, alias_files
            name_dirs = [root / self._only] if self._only else sorted(root.iterdir())
        except OSError as exc:  # the registry folder itself: nothing can be served from it
            raise StorageError(unreadable(str(root), exc)) from None
        for name_dir in name_dirs:
            try:
                if not name_dir.is_dir() or name_dir.name.startswith("."):
                    continue
                has_aliases = (name_dir / ALIASES).is_file()
                vdirs = sorted(name_dir.iterdir())
            except OSError as exc:  # another user's private model folder: refused, the others are served
                if NAME_RE.match(name_dir.name):
                    self._unlisted[name_dir.name] = unreadable(self._display(name_dir.name), exc)
                continue
            if has_aliases:
                alias_files[name_dir.name] = None  # small: read at every scan
            for vdir in vdirs:
                try:
                    if not vdir.is_dir() or vdir.name.startswith("."):
                        continue  # hidden temporary folders of in-progress writes
                except OSError:
                    pass  # listed but not even stat-able: _verify refuses it, naming why
                try:
                    fingerprint = tuple(sorted((f.name, st.st_size, st.st_mtime_ns) for f in vdir.iterdir()
                                               if f.is_file() and (st := f.stat())))
                except OSError:
                    fingerprint = None  # vanishing meanwhile, or unreadable: verify it now
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
        versions, unpublished = {}, {}
        for key, files in groups.items():
            if MANIFEST not in files:  # not published yet (or a killed write): not listed
                if NAME_RE.match(key[0]) and VERSION_RE.match(key[1]):
                    unpublished[key] = files
                continue
            versions[key] = tuple(sorted((fn, i["size"], i["tag"]) for fn, i in files.items()))
        self.unpublished = unpublished
        return versions, alias_files

    def remove_leftovers(self, older_than: float) -> list[str]:
        """Remove what killed writes left (returns what was removed, as paths or URLs).

        Local: the ``NAME/.tmp-*`` folders whose writer process is gone from this host at once, the
        others once untouched for ``older_than`` seconds (``bundle.remove_stale_temps``). Object store:
        the objects of every version the last scan listed without a manifest whose newest object is at
        least ``older_than`` seconds old (``bundle.stale_unpublished``; a live writer's newest object is
        never older than one file's upload). ``older_than`` = inf: only the gone writers' folders.
        """
        if not self.remote:
            return [str(p) for p in remove_stale_temps(self.root, older_than, self._only)]
        if older_than == float("inf"):
            return []
        objects = stale_unpublished(self.unpublished, older_than)
        if not objects:
            return []
        self.store.remove(objects)
        prefixes = sorted({"/".join(o.split("/")[:2]) for o in objects})
        for p in prefixes:
            self.unpublished.pop(tuple(p.split("/")), None)
        return [self.store.uri(p) for p in prefixes]

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
        except OSError as exc:  # another user's private folder or file: refused like a bad checksum
            return None, unreadable(where, exc)

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
            plain_modes(tmp)  # not mkdtemp's 0700: processes of other users may share the cache folder
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

    def listed(self) -> set[str]:
        """``NAME:VERSION`` of every version the last scan listed, served or refused."""
        return {f"{n}:{v}" for n, v in self._seen}

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
        except (BundleError, OSError) as exc:
            reason = str(exc) if isinstance(exc, BundleError) else unreadable(self._display(e.name, e.version), exc)
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
