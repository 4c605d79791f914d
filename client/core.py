"""The service's Python client: httpx underneath, numpy arrays in and out, typed problems, retries.

::

    from gpnarx.client import Client

    with Client("http://localhost:8000", api_key=None) as c:
        print([m["name"] for m in c.models()])
        p = c.predict("bouc-wen", u=u, fs=750.0, y=y, mc_paths=256)   # u, y: 1-D arrays
        p.mean, p.lower, p.upper, p.std                                # np.ndarray (output units)
        p.fit, p.coverage                                              # when y was sent

Methods mirror the routes: ``models()``, ``model(name, version=None)``, ``predict``, ``loops`` and
``novelty`` (``name, u=..., fs=..., y=None, version=None, y0=None, mc_paths=None, seed=None,
confidence=None, method=None, backend=None, start=None``), ``batch(requests)``, ``report(name,
version=None)``, ``health()`` and ``ready()``. ``AsyncClient`` has the same methods as coroutines.

Wire: by default the record goes as an NPZ body and the answer comes back as NPZ (``wire="npz"``;
``wire="json"`` sends and receives JSON, with gzip accepted). Either way the answers are
:class:`Answer` objects whose number lists (per the service's response schemas: ``mean``, ``lower``,
``upper``, ``std``, the loops' ``x`` and ``force``, ...) are float64 ``np.ndarray``.

Errors: every RFC 9457 problem detail raises the subclass of :class:`GpnarxError` that matches its
``type`` (``NotFound``, ``InvalidRequest``, ``TooLarge``, ``Overloaded``, ...; ``.status``,
``.detail``, ``.field``, ``.problem``). A 503 with ``Retry-After`` is retried after that many seconds
(at most ``retries`` times, each wait capped at ``max_retry_wait`` [s]) before ``Overloaded`` is
raised. In ``batch`` a failed slot is an exception *object* in the returned list, not raised.
"""
from __future__ import annotations

import asyncio
import io
import time
import typing
from typing import Any

import httpx
import numpy as np
from pydantic import BaseModel

from gpnarx.service.problems import SLUGS, TYPE_BASE
from gpnarx.service.schemas import LoopsResponse, NoveltyResponse, PredictResponse
from gpnarx.service.wire import NPZ_MEDIA_TYPE, json_loads_npz_meta
from gpnarx.storage.jsonsafe import dumps_json

_RESPONSES = {"predict": PredictResponse, "loops": LoopsResponse, "novelty": NoveltyResponse}
_OPTIONS = ("mc_paths", "seed", "confidence", "method", "backend", "start", "state", "return_state", "horizon")


# ---------------------------------------------------------------------------------------- errors
class GpnarxError(Exception):
    """A problem detail answered by the service (or a transport failure: ``status`` 0)."""

    status = 0

    def __init__(self, problem: dict):
        self.problem = dict(problem)
        self.status = int(problem.get("status") or self.status)
        self.title = problem.get("title", "")
        self.detail = problem.get("detail", "")
        self.field = problem.get("field")
        self.type = problem.get("type", "about:blank")
        super().__init__(f"{self.status} {self.title}: {self.detail}" if self.title else str(self.detail))


class BadRequest(GpnarxError):
    status = 400


class Unauthorized(GpnarxError):
    status = 401


class NotFound(GpnarxError):
    status = 404


class MethodNotAllowed(GpnarxError):
    status = 405


class RequestTimeout(GpnarxError):
    status = 408


class Conflict(GpnarxError):
    status = 409


class TooLarge(GpnarxError):
    status = 413


class UnsupportedMediaType(GpnarxError):
    status = 415


class InvalidRequest(GpnarxError):
    status = 422


class ClientClosedRequest(GpnarxError):
    status = 499


class InternalError(GpnarxError):
    status = 500


class Overloaded(GpnarxError):
    """503: the service's queue is full; ``retry_after`` [s] says when to come back."""

    status = 503

    @property
    def retry_after(self) -> float | None:
        return self.problem.get("retry_after")


class Timeout(GpnarxError):
    status = 504


_BY_STATUS = {c.status: c for c in (BadRequest, Unauthorized, NotFound, MethodNotAllowed, RequestTimeout, Conflict,
                                    TooLarge, UnsupportedMediaType, InvalidRequest, ClientClosedRequest, InternalError,
                                    Overloaded, Timeout)}
#: the exception class of each problem ``type`` the service uses (service.problems.SLUGS)
BY_TYPE = {TYPE_BASE + slug: _BY_STATUS[status] for status, slug in SLUGS.items() if status in _BY_STATUS}


def error_for(problem: dict) -> GpnarxError:
    """The typed exception of one problem detail (by its ``type``, else its ``status``)."""
    cls = BY_TYPE.get(str(problem.get("type"))) or _BY_STATUS.get(int(problem.get("status") or 0), GpnarxError)
    return cls(problem)


def _raise_for(r: httpx.Response) -> None:
    if r.status_code < 400:
        return
    try:
        problem = r.json()
        if not isinstance(problem, dict):
            raise ValueError
    except ValueError:
        problem = {"status": r.status_code, "title": r.reason_phrase, "detail": r.text[:300]}
    problem.setdefault("status", r.status_code)
    if r.status_code == 503 and "retry-after" in r.headers:
        problem.setdefault("retry_after", _retry_after(r))
    raise error_for(problem)


def _retry_after(r: httpx.Response) -> float | None:
    try:
        return max(0.0, float(r.headers["retry-after"]))
    except (KeyError, ValueError):
        return None


# ---------------------------------------------------------------------------------------- answers
class Answer(dict):
    """An answer: a dict whose keys are also attributes (``p.mean``); number lists are np.ndarray."""

    def __getattr__(self, key):
        try:
            return self[key]
        except KeyError:
            raise AttributeError(key) from None


def _float_or_null(ann) -> bool:
    """``float | None``: a number list that holds null through a gap (its nulls come back as NaN)."""
    origin = typing.get_origin(ann)
    return ((origin is typing.Union or str(origin) == "<class 'types.UnionType'>")
            and set(typing.get_args(ann)) == {float, type(None)})


def _array_fields(model: type[BaseModel]) -> dict:
    """{field: None (a list of numbers) | sub-model | (list, sub-model)} of a response schema."""
    out: dict = {}
    hints = typing.get_type_hints(model)
    for name in model.model_fields:
        ann = hints.get(name)
        origin, args = typing.get_origin(ann), typing.get_args(ann)
        if origin is typing.Union or str(origin) == "<class 'types.UnionType'>":
            inner = [a for a in args if a is not type(None)]
            ann = inner[0] if len(inner) == 1 else ann
            origin, args = typing.get_origin(ann), typing.get_args(ann)
        if origin is list and args and (args[0] is float or _float_or_null(args[0])):
            out[name] = None
        elif isinstance(ann, type) and issubclass(ann, BaseModel):
            out[name] = ann
        elif origin is list and args and isinstance(args[0], type) and issubclass(args[0], BaseModel):
            out[name] = (list, args[0])
    return out


def _to_arrays(d: Any, model: type[BaseModel]) -> Any:
    if not isinstance(d, dict):
        return d
    out = Answer(d)
    for name, kind in _array_fields(model).items():
        v = out.get(name)
        if v is None:
            continue
        if kind is None:
            out[name] = np.asarray([np.nan if x is None else x for x in v] if isinstance(v, list) else v,
                                   dtype=np.float64)
        elif isinstance(kind, tuple):
            out[name] = [_to_arrays(x, kind[1]) for x in v]
        else:
            out[name] = _to_arrays(v, kind)
    return out


def _answer(r: httpx.Response, operation: str) -> Answer:
    _raise_for(r)
    if r.headers.get("content-type", "").startswith(NPZ_MEDIA_TYPE):
        with np.load(io.BytesIO(r.content), allow_pickle=False) as z:
            d: dict = {}
            for k in z.files:
                a = z[k]
                if k == "json":
                    d.update(json_loads_npz_meta(a))
                elif a.ndim == 0:
                    d[k] = a.item()
                else:
                    d[k] = a
        return _to_arrays(d, _RESPONSES[operation])
    return _to_arrays(r.json(), _RESPONSES[operation])


# ---------------------------------------------------------------------------------------- requests
def _record_request(operation: str, name: str, version: str | None, u, fs, y, y0, options: dict, wire: str) -> dict:
    """httpx request arguments of a predict / loops / novelty call."""
    path = f"/v1/models/{name}/{operation}" if version is None else f"/v1/models/{name}/versions/{version}/{operation}"
    opts = {k: v for k, v in options.items() if v is not None and v is not False}
    arrays = {"u": u, "y": y, "y0": y0}
    if wire == "npz" and "state" not in opts:  # a stream's state token can be long: it goes in a JSON body
        buf = io.BytesIO()
        np.savez(buf, fs=np.float64(fs), **{k: np.asarray(v, dtype=np.float64) for k, v in arrays.items()
                                            if v is not None})
        params = {k: (str(v).lower() if isinstance(v, bool) else v) for k, v in opts.items()}
        return {"method": "POST", "url": path, "content": buf.getvalue(), "params": params,
                "headers": {"content-type": NPZ_MEDIA_TYPE, "accept": NPZ_MEDIA_TYPE}}
    body = {"fs": float(fs), **{k: np.asarray(v, dtype=np.float64) for k, v in arrays.items() if v is not None},
            **opts}
    accept = NPZ_MEDIA_TYPE if wire == "npz" else "application/json"
    return {"method": "POST", "url": path, "content": dumps_json(body),
            "headers": {"content-type": "application/json", "accept": accept}}


def _batch_item(item: dict) -> dict:
    return {k: (np.asarray(v, dtype=np.float64) if k in ("u", "y", "y0") else v) for k, v in item.items()
            if v is not None}


def _batch_answer(r: httpx.Response, requests: list[dict]) -> list:
    _raise_for(r)
    out = []
    for item, res in zip(requests, r.json()["results"]):
        if isinstance(res, dict) and "status" in res and "detail" in res and "type" in res:
            out.append(error_for(res))
        else:
            out.append(_to_arrays(res, _RESPONSES[item.get("operation", "predict")]))
    return out


class _Base:
    def __init__(self, base_url: str, api_key: str | None = None, *, timeout: float = 300.0, retries: int = 3,
                 max_retry_wait: float = 30.0, wire: str = "npz"):
        if wire not in ("npz", "json"):
            raise ValueError(f"wire must be 'npz' or 'json', got {wire!r}")
        self.base_url = base_url.rstrip("/")
        self.retries = int(retries)
        self.max_retry_wait = float(max_retry_wait)
        self.wire = wire
        self._headers = {"accept-encoding": "gzip"}
        if api_key:
            self._headers["X-API-Key"] = api_key
        self._timeout = timeout

    def _wait(self, r: httpx.Response, attempt: int) -> float | None:
        """Seconds to wait before retrying ``r``, or None when it is not retried."""
        if r.status_code != 503 or attempt >= self.retries:
            return None
        after = _retry_after(r)
        return None if after is None else min(after, self.max_retry_wait)


class Client(_Base):
    """Synchronous client (see the module doc). Use as a context manager or call ``close()``."""

    def __init__(self, base_url: str, api_key: str | None = None, *, transport: httpx.BaseTransport | None = None,
                 **kw):
        super().__init__(base_url, api_key, **kw)
        self._http = httpx.Client(base_url=self.base_url, headers=self._headers, timeout=self._timeout,
                                  transport=transport)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        self._http.close()

    def _send(self, method: str, url: str, **kw) -> httpx.Response:
        attempt = 0
        while True:
            r = self._http.request(method, url, **kw)
            wait = self._wait(r, attempt)
            if wait is None:
                return r
            time.sleep(wait)
            attempt += 1

    def _get(self, url: str) -> Any:
        r = self._send("GET", url)
        _raise_for(r)
        return r.json()

    # routes
    def health(self) -> dict:
        return self._get("/health/live")

    def ready(self) -> dict:
        return self._get("/health/ready")

    def models(self) -> list[dict]:
        """The loaded models (name, versions, latest, fs [Hz], units, lags, novelty)."""
        return self._get("/v1/models")["models"]

    def model(self, name: str, version: str | None = None) -> dict:
        """One version's metadata (latest by default)."""
        return self._get(f"/v1/models/{name}" if version is None else f"/v1/models/{name}/versions/{version}")

    def report(self, name: str, version: str | None = None) -> str:
        """The training report (self-contained HTML)."""
        r = self._send("GET", f"/v1/models/{name}/report" if version is None
                       else f"/v1/models/{name}/versions/{version}/report")
        _raise_for(r)
        return r.text

    def _record(self, operation, name, u, fs, y=None, version=None, y0=None, **options) -> Answer:
        req = _record_request(operation, name, version, u, fs, y, y0, options, self.wire)
        return _answer(self._send(req.pop("method"), req.pop("url"), **req), operation)

    def predict(self, name: str, u, fs: float, y=None, *, version: str | None = None, y0=None,
                mc_paths: int | None = None, seed: int | None = None, confidence: float | None = None,
                method: str | None = None, backend: str | None = None, start: str | None = None,
                state: str | None = None, return_state: bool = False, horizon: int | None = None) -> Answer:
        """Free-run prediction of ``u`` (input units, sampled at ``fs`` [Hz]): ``mean``, ``lower``, ``upper``,
        ``std`` (output units, np.ndarray) and, with the measured ``y``, ``fit`` [%], ``rmse``, ``coverage`` [%].
        A stream: ``return_state=True`` returns ``state``; pass it as ``state`` with the next chunk.
        ``horizon``: k-step-ahead prediction, the run restarted from the measured ``y`` every k samples (the answer
        says ``horizon``). NaN samples in ``u`` or ``y`` are gaps: the answer is NaN through them and lists
        ``gaps``."""
        return self._record("predict", name, u, fs, y, version, y0, mc_paths=mc_paths, seed=seed,
                            confidence=confidence, method=method, backend=backend, start=start, state=state,
                            return_state=return_state, horizon=horizon)

    def loops(self, name: str, u, fs: float, y=None, *, version: str | None = None, y0=None,
              mc_paths: int | None = None, seed: int | None = None, confidence: float | None = None,
              method: str | None = None, backend: str | None = None, start: str | None = None,
              state: str | None = None, return_state: bool = False) -> Answer:
        """Restoring-force loops (``predicted``/``lower``/``upper``/``measured``: ``x``, ``force`` as np.ndarray)
        and per-cycle energies."""
        return self._record("loops", name, u, fs, y, version, y0, mc_paths=mc_paths, seed=seed,
                            confidence=confidence, method=method, backend=backend, start=start, state=state,
                            return_state=return_state)

    def novelty(self, name: str, u, fs: float, y, *, version: str | None = None, y0=None,
                mc_paths: int | None = None, seed: int | None = None, confidence: float | None = None,
                method: str | None = None, backend: str | None = None, start: str | None = None,
                state: str | None = None, return_state: bool = False) -> Answer:
        """Novelty ``score``, ``threshold`` and ``verdict`` of the measured record (``u``, ``y``)."""
        return self._record("novelty", name, u, fs, y, version, y0, mc_paths=mc_paths, seed=seed,
                            confidence=confidence, method=method, backend=backend, start=start, state=state,
                            return_state=return_state)

    def batch(self, requests: list[dict]) -> list:
        """Many records (each a dict: ``model``, ``operation``, ``u``, ``fs``, ...; arrays allowed): one
        :class:`Answer` or :class:`GpnarxError` *object* per request, in order."""
        r = self._send("POST", "/v1/batch", content=dumps_json({"requests": [_batch_item(i) for i in requests]}),
                       headers={"content-type": "application/json"})
        return _batch_answer(r, requests)


class AsyncClient(_Base):
    """asyncio client: the methods of :class:`Client` as coroutines. ``async with AsyncClient(...) as c``."""

    def __init__(self, base_url: str, api_key: str | None = None, *,
                 transport: httpx.AsyncBaseTransport | None = None, **kw):
        super().__init__(base_url, api_key, **kw)
        self._http = httpx.AsyncClient(base_url=self.base_url, headers=self._headers, timeout=self._timeout,
                                       transport=transport)

    async def __aenter__(self):
        return self

    async def __aexit__(self, *exc):
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    async def _send(self, method: str, url: str, **kw) -> httpx.Response:
        attempt = 0
        while True:
            r = await self._http.request(method, url, **kw)
            wait = self._wait(r, attempt)
            if wait is None:
                return r
            await asyncio.sleep(wait)
            attempt += 1

    async def _get(self, url: str) -> Any:
        r = await self._send("GET", url)
        _raise_for(r)
        return r.json()

    async def health(self) -> dict:
        return await self._get("/health/live")

    async def ready(self) -> dict:
        return await self._get("/health/ready")

    async def models(self) -> list[dict]:
        return (await self._get("/v1/models"))["models"]

    async def model(self, name: str, version: str | None = None) -> dict:
        return await self._get(f"/v1/models/{name}" if version is None else f"/v1/models/{name}/versions/{version}")

    async def report(self, name: str, version: str | None = None) -> str:
        r = await self._send("GET", f"/v1/models/{name}/report" if version is None
                             else f"/v1/models/{name}/versions/{version}/report")
        _raise_for(r)
        return r.text

    async def _record(self, operation, name, u, fs, y=None, version=None, y0=None, **options) -> Answer:
        req = _record_request(operation, name, version, u, fs, y, y0, options, self.wire)
        return _answer(await self._send(req.pop("method"), req.pop("url"), **req), operation)

    async def predict(self, name: str, u, fs: float, y=None, *, version: str | None = None, y0=None,
                      **options) -> Answer:
        """See :meth:`Client.predict`."""
        return await self._record("predict", name, u, fs, y, version, y0, **_checked(options))

    async def loops(self, name: str, u, fs: float, y=None, *, version: str | None = None, y0=None,
                    **options) -> Answer:
        """See :meth:`Client.loops`."""
        return await self._record("loops", name, u, fs, y, version, y0, **_checked(options))

    async def novelty(self, name: str, u, fs: float, y, *, version: str | None = None, y0=None,
                      **options) -> Answer:
        """See :meth:`Client.novelty`."""
        return await self._record("novelty", name, u, fs, y, version, y0, **_checked(options))

    async def batch(self, requests: list[dict]) -> list:
        """See :meth:`Client.batch`."""
        r = await self._send("POST", "/v1/batch",
                             content=dumps_json({"requests": [_batch_item(i) for i in requests]}),
                             headers={"content-type": "application/json"})
        return _batch_answer(r, requests)


def _checked(options: dict) -> dict:
    unknown = set(options) - set(_OPTIONS)
    if unknown:
        raise TypeError(f"unknown option(s) {', '.join(sorted(unknown))}; use {', '.join(_OPTIONS)}")
    return options
