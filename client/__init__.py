"""``gpnarx.client``: the first-party Python client of the service (extra ``client``).

``Client(base_url, api_key=None)`` (sync) and ``AsyncClient`` (asyncio) call the HTTP API with httpx
and hand numpy arrays in and out; see ``gpnarx.client.core``.
"""
from .core import (
    Answer,
    AsyncClient,
    BadRequest,
    Client,
    ClientClosedRequest,
    Conflict,
    GpnarxError,
    InternalError,
    InvalidRequest,
    MethodNotAllowed,
    NotFound,
    Overloaded,
    RequestTimeout,
    Timeout,
    TooLarge,
    Unauthorized,
    UnsupportedMediaType,
    error_for,
)

__all__ = ["Answer", "AsyncClient", "BadRequest", "Client", "ClientClosedRequest", "Conflict", "GpnarxError",
           "InternalError", "InvalidRequest", "MethodNotAllowed", "NotFound", "Overloaded", "RequestTimeout",
           "Timeout", "TooLarge", "Unauthorized", "UnsupportedMediaType", "error_for"]
