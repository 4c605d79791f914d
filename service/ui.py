"""The service's pages and what their routes (``service.routers.ui``) need, with no asset from
outside the service.

Routes (``service.routers.ui``; the app mounts ``STATIC_DIR`` at /static)::

    GET  /ui                                          the engineers' page (static/ui/), not in OpenAPI
    GET  /static/...                                  its files, vendored libraries and example records
    GET  /docs, /docs/oauth2-redirect, /redoc         Swagger UI and ReDoc from static/vendor/
    GET  /v1/models/{name}/report                     the latest version's training report (HTML)
    GET  /v1/models/{name}/versions/{version}/report  one version's training report (HTML)
    POST /v1/records/parse                            an uploaded record file -> {u, y, fs, ...} JSON

Reports are served self-contained: ``training.report`` embeds its figures as ``data:`` URIs, and an
older report's relative image links (``record_x.png`` next to ``report.html``) are inlined here at
serve time, so the page (or a saved copy) opens without the bundle folder. Reports are sent with a
Content-Security-Policy that allows no script and no outside load.

Record files are parsed by :mod:`gpnarx.storage.record_formats` (the same parsers as the CLI's
``storage.record_files``): CSV, NPZ, NPY, MATLAB v5 .mat, or the two files of an LMS Test.Lab export.

The vendored libraries (versions, sources and checksums in ``static/vendor/VENDORED.md``): uPlot
(plots on the page), swagger-ui-dist and redoc (API documentation).
"""
from __future__ import annotations

import base64
import functools
import re
from html import escape as html_escape
from pathlib import Path, PurePath
from typing import Annotated
from urllib.parse import unquote

from fastapi import Path as PathParam
from fastapi import Request
from pydantic import BaseModel, Field
from starlette.datastructures import UploadFile

from gpnarx.storage.record_formats import LMS_INPUT, LMS_OUTPUT, parse_lms, parse_record

from .problems import ProblemError
from .schemas import NAME_PATTERN, VERSION_PATTERN

STATIC_DIR = Path(__file__).resolve().parent / "static"
REPORT_FILE = Path("report") / "report.html"  # inside a bundle folder (storage.bundle attach_dir)
#: The training report may load nothing from outside itself (its figures are data: URIs) and runs no script.
REPORT_CSP = "default-src 'none'; img-src data:; style-src 'unsafe-inline'; base-uri 'none'; form-action 'none'"
#: The page loads only the service's own files and calls only the service.
PAGE_CSP = ("default-src 'self'; img-src 'self' data: blob:; style-src 'self' 'unsafe-inline'; "
            "script-src 'self'; connect-src 'self'; frame-src blob:; object-src 'none'; base-uri 'none'")
#: ReDoc runs from its vendored bundle; its sidebar's "Redocly" logo (an outside image) is refused by the
#: browser instead of being fetched, and the component hides itself when the image fails.
REDOC_CSP = ("default-src 'self'; img-src 'self' data:; style-src 'self' 'unsafe-inline'; script-src 'self'; "
             "worker-src 'self' blob:; font-src 'self' data:; connect-src 'self'; object-src 'none'; base-uri 'none'")
_INLINE_TYPES = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".gif": "image/gif",
                 ".svg": "image/svg+xml", ".webp": "image/webp"}
_IMG_SRC = re.compile(r"""(<img\b[^>]*?\bsrc\s*=\s*)(["'])([^"']*)\2""", re.IGNORECASE)
MAX_UPLOAD_FILES = 2
_FS_PROBLEMS = ("fs given as", "fs must be a number", "fs must be a finite", "the file holds no sampling frequency")

NameP = Annotated[str, PathParam(pattern=NAME_PATTERN, description="Model name.")]
VersionP = Annotated[str, PathParam(pattern=VERSION_PATTERN, description="Model version (1, 2, ...) or alias "
                                                                         "(latest, production, ...).")]


# ------------------------------------------------------------------------------------------ reports
def inline_images(html: str, folder: Path) -> str:
    """``html`` with each relative ``<img src>`` that names an image file inside ``folder`` as a data URI.

    Absolute URLs, data URIs and links that leave ``folder`` (``../``) are left as they are.
    """
    root = folder.resolve()

    def repl(m: re.Match) -> str:
        src = m.group(3).strip()
        if not src or src.startswith(("data:", "/", "#")) or re.match(r"^[A-Za-z][A-Za-z0-9+.-]*:", src):
            return m.group(0)
        path = (root / unquote(src.split("?", 1)[0].split("#", 1)[0])).resolve()
        mime = _INLINE_TYPES.get(path.suffix.lower())
        if mime is None or not path.is_relative_to(root) or not path.is_file():
            return m.group(0)
        data = base64.b64encode(path.read_bytes()).decode("ascii")
        return f"{m.group(1)}{m.group(2)}data:{mime};base64,{data}{m.group(2)}"

    return _IMG_SRC.sub(repl, html)


def read_report(bundle_path: Path) -> str | None:
    """The bundle's training report as self-contained HTML, or None when it has none."""
    path = Path(bundle_path) / REPORT_FILE
    if not path.is_file():
        return None
    return inline_images(path.read_text(encoding="utf-8", errors="replace"), path.parent)


# ------------------------------------------------------------------------------------------ records
class ParsedUnits(BaseModel):
    u: str = Field("", description="Unit of u as stated in the file ('' when not stated).")
    y: str = Field("", description="Unit of y as stated in the file ('' when not stated).")


class ParsedRecord(BaseModel):
    """A record file's contents, ready to send to predict, loops or novelty."""

    name: str = Field(..., description="Record name (the file's stem, the NPZ's `name`, or the LMS folder).")
    format: str = Field(..., description="csv, npz, npy, mat or lms-testlab.")
    files: list[str] = Field(..., description="Names of the uploaded files that were read.")
    fs: float = Field(..., description="Sampling frequency [Hz].")
    n_samples: int
    units: ParsedUnits
    u: list[float] = Field(..., description="Input samples.")
    y: list[float] | None = Field(None, description="Output samples, or null when the file holds only u.")
    meta: dict = Field(default_factory=dict, description="What the file says about itself (LMS channels, run name).")


_PARSE_DESC = (
    "Parse an uploaded record file into JSON, as `storage.record_files` reads files for the CLI: send "
    "`multipart/form-data` with one file in `files` (`.csv` with a header naming `time`, `u`, `y`; `.npz` "
    "with arrays `u`, `y`, scalar `fs`; `.npy`; MATLAB v5 `.mat` with `u`, `y`, `fs`) or the two files of an "
    "LMS Test.Lab export (`Time.mat` and `TimeShaker.mat`, both in `files`), and `fs` [Hz] when the file "
    "carries no sampling information (a CSV without a time column). The answer's `u`, `y` and `fs` can be "
    "sent as they are to predict, loops or novelty. Records longer than the service's sample limit "
    "(GPNARX_MAX_SAMPLES) are refused with 413; bodies above GPNARX_MAX_BODY_BYTES with 413.")
_PARSE_BODY = {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": {
    "type": "object", "required": ["files"],
    "properties": {
        "files": {"type": "array", "items": {"type": "string", "format": "binary"}, "minItems": 1,
                  "maxItems": MAX_UPLOAD_FILES,
                  "description": "One record file, or the two files of an LMS export (Time.mat, TimeShaker.mat)."},
        "fs": {"type": "number", "exclusiveMinimum": 0,
               "description": "Sampling frequency [Hz]; needed only when the file has none, checked otherwise."}}}}}}}


def _fname(upload: UploadFile) -> str:
    return PurePath((upload.filename or "").replace("\\", "/")).name


def _folder(upload: UploadFile) -> str:
    parent = PurePath((upload.filename or "").replace("\\", "/")).parent.name
    return parent or "LMS export"


def parse_uploads(uploads: list[tuple[str, str, bytes]], fs: float | None, max_samples: int | None = None,
                  max_bytes: int | None = None):
    """(file name, folder name, contents) of 1 or 2 uploaded files -> ``(Record, format)``; max_samples
    [samples per signal] and max_bytes [bytes decompressed]: checked from each file's headers before it is
    parsed (``storage.record_formats.check_bounds``, RecordTooLarge)."""
    bounds = {"max_samples": max_samples, "max_bytes": max_bytes}
    names = [n for n, _, _ in uploads]
    lms = {LMS_INPUT[0], LMS_OUTPUT[0]}
    if len(uploads) == 2 or (len(uploads) == 1 and names[0] in lms):
        if sorted(names) != sorted(lms):
            raise ProblemError(422, f"two files are read only as an LMS Test.Lab export, {LMS_OUTPUT[0]} and "
                                    f"{LMS_INPUT[0]}; got {', '.join(names)}", "files")
        by = {n: (folder, data) for n, folder, data in uploads}
        folder = by[LMS_OUTPUT[0]][0]
        rec = parse_lms(by[LMS_INPUT[0]][1], by[LMS_OUTPUT[0]][1], fs=fs, name=folder, source=folder,
                        shaker_source=LMS_INPUT[0], time_source=LMS_OUTPUT[0], **bounds)
        return rec, "lms-testlab"
    name, _, data = uploads[0]
    rec = parse_record(data, name, fs=fs, **bounds)
    if rec.u.ndim != 1 or (rec.y is not None and rec.y.ndim != 1):
        chans = [c.name for c in rec.input_channels() + rec.output_channels()]
        raise ProblemError(422, f"{name} holds several channels ({', '.join(chans)}); the service answers "
                                "single-channel records (answers per channel are not built yet)", "files")
    return rec, PurePath(name).suffix.lower().lstrip(".")


# ------------------------------------------------------------------------------------------ page
@functools.lru_cache(maxsize=1)
def _page_template() -> str:
    return (STATIC_DIR / "ui" / "index.html").read_text(encoding="utf-8")


def _root(request: Request) -> str:
    """The app's mount prefix (uvicorn --root-path, a proxy's prefix), escaped for HTML attributes."""
    return html_escape(request.scope.get("root_path", "").rstrip("/"), quote=True)


__all__ = ["inline_images", "read_report", "parse_uploads", "ParsedRecord", "STATIC_DIR"]
