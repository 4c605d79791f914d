"""The engineers' page, the API documentation pages, training reports and record-file parsing.

``pages`` (/ui, /docs, /redoc) is open; ``router`` (the /v1 report and record routes) needs the
API key when one is set. The helpers (report reading and inlining, upload parsing) are in
``service.ui``; the app mounts ``service.ui.STATIC_DIR`` at /static.
"""
from __future__ import annotations

import asyncio
from pathlib import PurePath

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from starlette.datastructures import UploadFile
from starlette.responses import HTMLResponse

from gpnarx.storage.record_formats import FORMATS, RecordFileError, RecordTooLarge

from ..answers import answer
from ..deps import V1, SettingsDep, StateDep
from ..problems import ProblemError
from ..responses import conditional
from ..state import ServiceState
from ..ui import (
    _FS_PROBLEMS,
    _PARSE_BODY,
    _PARSE_DESC,
    MAX_UPLOAD_FILES,
    PAGE_CSP,
    REDOC_CSP,
    REPORT_CSP,
    REPORT_FILE,
    NameP,
    ParsedRecord,
    VersionP,
    _fname,
    _folder,
    _page_template,
    _root,
    parse_uploads,
    read_report,
)
from ..wire import IMMUTABLE

pages = APIRouter()
router = APIRouter(prefix="/v1", dependencies=V1)

problems = {
    401: {"description": "API key missing or wrong (only when GPNARX_API_KEY is set)"},
    404: {"description": "No such model, version or training report"},
    422: {"description": "Invalid model name or version"},
}


# ---------------------------------------------------------------- page and documentation
@pages.get("/ui", include_in_schema=False)
async def ui_page(request: Request):
    html = _page_template().replace("{{root}}", _root(request))
    return HTMLResponse(html, headers={"Content-Security-Policy": PAGE_CSP, "Cache-Control": "no-cache"})


@pages.get("/docs", include_in_schema=False)
async def swagger_ui(request: Request):
    root = _root(request)
    return get_swagger_ui_html(
        openapi_url=root + request.app.openapi_url, title=f"{request.app.title} - Swagger UI",
        swagger_js_url=f"{root}/static/vendor/swagger-ui/swagger-ui-bundle.js",
        swagger_css_url=f"{root}/static/vendor/swagger-ui/swagger-ui.css",
        swagger_favicon_url=f"{root}/static/vendor/swagger-ui/favicon-32x32.png",
        oauth2_redirect_url=f"{root}/docs/oauth2-redirect",
        # no call to the online validator (offline plant networks)
        swagger_ui_parameters={"validatorUrl": None, "persistAuthorization": False})


@pages.get("/docs/oauth2-redirect", include_in_schema=False)
async def swagger_ui_redirect():
    return get_swagger_ui_oauth2_redirect_html()


@pages.get("/redoc", include_in_schema=False)
async def redoc(request: Request):
    root = _root(request)
    page = get_redoc_html(openapi_url=root + request.app.openapi_url, title=f"{request.app.title} - ReDoc",
                          redoc_js_url=f"{root}/static/vendor/redoc/redoc.standalone.js",
                          redoc_favicon_url=f"{root}/static/vendor/swagger-ui/favicon-32x32.png",
                          with_google_fonts=False)
    page.headers["Content-Security-Policy"] = REDOC_CSP
    return page


# ---------------------------------------------------------------- reports
async def report_of(state: ServiceState, name: str, version: str | None, request: Request | None = None):
    bundle = state.lookup(name, version, build=False)  # the report is a file: no model needed
    html = await asyncio.to_thread(read_report, bundle.path)
    if html is None:
        raise ProblemError(404, f"model {bundle.name} version {bundle.version} has no training report "
                                f"(no {REPORT_FILE.as_posix()} in its bundle; bundles written by `gpnarx train` "
                                f"carry one)", "version")
    headers = {"Content-Security-Policy": REPORT_CSP, "X-Content-Type-Options": "nosniff"}
    if request is None:
        return HTMLResponse(html, headers=headers)
    # a version's report is a file of an immutable bundle: cached for good, revalidated by its ETag
    return conditional(request, html.encode(), "text/html; charset=utf-8", IMMUTABLE, headers)


report_responses = {200: {"content": {"text/html": {"schema": {"type": "string"}}},
                          "description": "The training report, one self-contained HTML page (figures embedded)"},
                    **problems}


@router.get("/models/{name}/report", tags=["models"], operation_id="get_report",
            response_class=HTMLResponse, responses=report_responses,
            summary="Training report of a model's latest version (self-contained HTML)")
async def get_report(state: StateDep, name: NameP):
    return await report_of(state, name, None)


version_report_responses = {
    **report_responses,
    200: {**report_responses[200], "headers": {
        "ETag": {"description": "Weak validator of the report; send it back in If-None-Match for a 304",
                 "schema": {"type": "string"}},
        "Cache-Control": {"description": "`max-age=31536000, immutable` (`private, ...` behind an API key)",
                          "schema": {"type": "string"}}}},
    304: {"description": "Not modified: the request's If-None-Match names the report's ETag (no body)"},
}


@router.get("/models/{name}/versions/{version}/report", tags=["models"], operation_id="get_report_version",
            response_class=HTMLResponse, responses=version_report_responses,
            summary="Training report of one version (self-contained HTML; ETag, immutable, If-None-Match gives 304)")
async def get_report_version(request: Request, state: StateDep, name: NameP, version: VersionP):
    return await report_of(state, name, version, request)


# ---------------------------------------------------------------- record files
@router.post("/records/parse", tags=["records"], operation_id="parse_record", response_model=ParsedRecord,
             summary="Parse an uploaded record file (CSV, NPZ, NPY, MAT, LMS export) into u, y, fs",
             description=_PARSE_DESC, openapi_extra=_PARSE_BODY,
             responses={400: {"description": "Not a multipart/form-data body"},
                        401: problems[401],
                        413: {"description": "Body or record above the service's limits"},
                        415: {"description": "Body is not multipart/form-data"},
                        422: {"description": "Missing file, unreadable record, or bad fs"}})
async def parse_record_file(request: Request, settings: SettingsDep):
    ctype = request.headers.get("content-type", "")
    if not ctype.lower().startswith("multipart/form-data"):
        raise ProblemError(415, f"the body must be multipart/form-data with the record in `files`, got "
                                f"{ctype[:100]!r}", "body")
    try:
        form = await request.form(max_files=MAX_UPLOAD_FILES, max_fields=4)
    except Exception as exc:  # noqa: BLE001 - malformed multipart or too many parts
        raise ProblemError(400, f"the multipart body could not be read: {exc}"[:300], "body") from None
    try:
        uploads = [f for f in form.getlist("files") if isinstance(f, UploadFile)]
        if not uploads:
            raise ProblemError(422, "send the record file in the multipart field `files`", "files")
        fs = None
        raw_fs = form.get("fs")
        if isinstance(raw_fs, str) and raw_fs.strip():
            try:
                fs = float(raw_fs)
            except ValueError:
                raise ProblemError(422, f"fs must be a number in Hz, got {raw_fs[:30]!r}", "fs") from None
        files = [(_fname(f), _folder(f), await f.read()) for f in uploads]
    finally:
        await form.close()
    for name, _, _ in files:
        if PurePath(name).suffix.lower() not in FORMATS:
            raise ProblemError(422, f"{name or '(no name)'}: unsupported record format; use "
                                    f"{', '.join(FORMATS)} or the two files of an LMS export", "files")
    try:
        # at most GPNARX_MAX_SAMPLES per signal and GPNARX_MAX_BODY_BYTES decompressed (what an uncompressed upload
        # may hold), decided from the files' headers before anything is decompressed (RecordTooLarge, a 413)
        rec, fmt = await asyncio.to_thread(parse_uploads, files, fs, settings.max_samples, settings.max_body_bytes)
    except RecordTooLarge as exc:
        setting = "GPNARX_MAX_SAMPLES" if exc.unit == "samples" else "GPNARX_MAX_BODY_BYTES"
        raise ProblemError(413, f"{exc} ({setting}): send a shorter part of it", "files", limit=exc.limit) from None
    except RecordFileError as exc:
        field = "fs" if exc.problem.startswith(_FS_PROBLEMS) else "files"
        raise ProblemError(422, str(exc), field) from None
    if rec.n > settings.max_samples:
        raise ProblemError(413, f"the record holds {rec.n} samples; the limit is {settings.max_samples} "
                                f"(GPNARX_MAX_SAMPLES): send a shorter part of it", "files",
                           limit=settings.max_samples)
    return answer(request, {"name": rec.name, "format": fmt, "files": [n for n, _, _ in files],
                            "fs": rec.fs, "n_samples": rec.n,
                            "units": {"u": rec.units.get("u", ""), "y": rec.units.get("y", "")},
                            "u": rec.u, "y": rec.y,
                            "meta": {k: v for k, v in rec.meta.items() if isinstance(v, (str, int, float))}})


