"""Where a registry lives: a local folder, or objects behind an fsspec URL, and the local cache.

A registry location is a plain path, a ``file://`` URL (both are local folders: ``as_local``) or
any other fsspec URL such as ``s3://bucket/prefix`` or ``gs://bucket/prefix`` (``RemoteStore``).
fsspec and the protocol's own package (s3fs for ``s3://``, gcsfs for ``gs://``) are needed only
for such URLs: ``pip install 'gpnarx[s3]'``.

Object-store credentials and endpoints come from where the protocol's package looks (for S3: the
usual ``AWS_ACCESS_KEY_ID``/``AWS_SECRET_ACCESS_KEY``/``AWS_ENDPOINT_URL`` variables or a profile);
``GPNARX_STORAGE_OPTIONS`` (a JSON object) is passed to fsspec as storage options on top, e.g.
``{"endpoint_url": "http://127.0.0.1:9000"}`` or ``{"anon": true}``.

Verified copies of remote bundle files are kept under ``cache_root()``: ``$GPNARX_CACHE`` or
``$XDG_CACHE_HOME/gpnarx/objects`` (default ``~/.cache/gpnarx/objects``), one folder per registry
URL. Nothing here knows the bundle format (``storage.bundle`` does); this module moves bytes and
names objects.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path

URL_RE = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]*)://")
OPTIONS_ENV = "GPNARX_STORAGE_OPTIONS"
CACHE_ENV = "GPNARX_CACHE"


class StorageError(OSError):
    """An object store cannot be reached, or an object cannot be read or written (the message names it)."""


def is_url(spec) -> bool:
    return isinstance(spec, str) and URL_RE.match(spec) is not None


def as_local(spec) -> Path | None:
    """The folder of a local registry location (a path or a ``file://`` URL); None for any other URL."""
    if isinstance(spec, os.PathLike):
        return Path(spec)
    spec = str(spec)
    m = URL_RE.match(spec)
    if m is None:
        return Path(spec).expanduser()
    if m.group(1).lower() == "file":
        rest = spec[m.end():]
        if rest.startswith("localhost/"):
            rest = rest[len("localhost"):]
        return Path(rest).expanduser()
    return None


def options_from_env(environ=None) -> dict:
    """fsspec storage options from ``GPNARX_STORAGE_OPTIONS`` (a JSON object; empty when unset)."""
    raw = (os.environ if environ is None else environ).get(OPTIONS_ENV, "").strip()
    if not raw:
        return {}
    try:
        opts = json.loads(raw)
    except json.JSONDecodeError as exc:
        raise StorageError(f"{OPTIONS_ENV} is not valid JSON ({exc})") from None
    if not isinstance(opts, dict):
        raise StorageError(f"{OPTIONS_ENV} must be a JSON object of fsspec storage options")
    return opts


def cache_root(environ=None) -> Path:
    env = os.environ if environ is None else environ
    if env.get(CACHE_ENV):
        return Path(env[CACHE_ENV]).expanduser()
    return Path(env.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "gpnarx" / "objects"


def cache_dir_for(url: str) -> Path:
    """The cache folder of one registry URL (readable name plus a hash, so two URLs never share one)."""
    slug = re.sub(r"[^A-Za-z0-9._-]+", "_", url)[:48].strip("_") or "registry"
    return cache_root() / f"{slug}-{hashlib.sha256(url.encode()).hexdigest()[:12]}"


def _tag(info: dict):
    """What changes when an object is rewritten: ETag / md5 / generation where the store gives one, else mtime."""
    for key in ("ETag", "etag", "md5Hash", "generation", "mtime", "LastModified", "last_modified", "created"):
        v = info.get(key)
        if v is not None:
            return v if isinstance(v, (str, int, float)) else str(v)
    return None


def _mtime(info: dict) -> float | None:
    for key in ("LastModified", "last_modified", "mtime", "created", "updated", "timeCreated"):
        v = info.get(key)
        if v is None:
            continue
        if hasattr(v, "timestamp"):
            return float(v.timestamp())
        if isinstance(v, (int, float)):
            return float(v)
        try:
            import datetime as _dt

            return _dt.datetime.fromisoformat(str(v).replace("Z", "+00:00")).timestamp()
        except ValueError:
            continue
    return None


class RemoteStore:
    """The objects under one fsspec URL, addressed by paths relative to it (``NAME/VERSION/file``)."""

    def __init__(self, url: str, storage_options: dict | None = None):
        try:
            import fsspec
        except ImportError:
            raise StorageError(f"registry {url}: object-store registries need fsspec "
                               "(pip install 'gpnarx[s3]')") from None
        self.url = url.rstrip("/")
        opts = options_from_env() if storage_options is None else dict(storage_options)
        try:
            self.fs, root = fsspec.core.url_to_fs(self.url, **opts)
        except ImportError as exc:
            raise StorageError(f"registry {url}: {exc} (for s3:// URLs: pip install 'gpnarx[s3]')") from None
        except (ValueError, TypeError) as exc:
            raise StorageError(f"registry {url}: {exc}") from None
        self.root = root.rstrip("/")

    def __repr__(self) -> str:
        return f"RemoteStore({self.url!r})"

    def uri(self, rel: str = "") -> str:
        return f"{self.url}/{rel}" if rel else self.url

    def _key(self, rel: str) -> str:
        return f"{self.root}/{rel}" if rel else self.root

    def _call(self, what: str, rel: str, fn, *args):
        try:
            return fn(*args)
        except StorageError:
            raise
        except FileNotFoundError:
            raise StorageError(f"{self.uri(rel)}: not found ({what})") from None
        except Exception as exc:  # noqa: BLE001 - every store's client errors become one clear line
            text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
            raise StorageError(f"{self.uri(rel)}: {what} failed ({type(exc).__name__}"
                               f"{': ' + text[:300] if text else ''})") from None

    def listing(self, under: str = "") -> dict[str, dict]:
        """Every object under ``under`` (relative to the root): {relative path: {size, tag, mtime}}.

        One recursive listing (on S3, ListObjectsV2 pages); fsspec's listing cache is dropped first,
        so objects written by other processes are seen. A prefix with no object lists as empty.
        """
        key = self._key(under.strip("/"))

        def find():
            self.fs.invalidate_cache()
            try:
                return self.fs.find(key, detail=True)
            except FileNotFoundError as exc:  # an empty prefix lists as {}; this is a missing bucket
                raise StorageError(f"{self.uri(under)}: listing failed ({exc})") from None

        found = self._call("listing", under, find)
        out = {}
        strip = self.root.lstrip("/")
        for path, info in found.items():
            p = str(path).lstrip("/")
            if not p.startswith(strip + "/") or info.get("type", "file") != "file":
                continue
            rel = p[len(strip) + 1:]
            out[rel] = {"size": int(info.get("size") or info.get("Size") or 0), "tag": _tag(info),
                        "mtime": _mtime(info)}
        return out

    def read_bytes(self, rel: str) -> bytes:
        return self._call("read", rel, self.fs.cat_file, self._key(rel))

    def download(self, rel: str, dest: Path) -> None:
        self._call("download", rel, self.fs.get_file, self._key(rel), str(dest))

    def put_bytes(self, rel: str, data: bytes) -> None:
        """One object written in one request (atomic on object stores: readers see old or new)."""
        self._call("write", rel, self.fs.pipe_file, self._key(rel), data)

    def put_file(self, src: Path, rel: str) -> None:
        self._call("upload", rel, self.fs.put_file, str(src), self._key(rel))

    def remove(self, rels: list[str]) -> None:
        if rels:
            self._call("remove", rels[0], self.fs.rm, [self._key(r) for r in rels])
