"""Answers checked against their routes' response models, then rendered by ``render_json``.

A route names its answer's model once, as ``response_model=`` of its decorator or of ``add_api_route`` (the OpenAPI
document shows it). FastAPI would validate a returned dict against it and then serialise it itself, copying every
numpy array into Python floats and reordering the members; so the routes return ``answer(request, body)``: the body
is validated by the route's model (``validate``) and rendered as it is (``responses.render_json``: arrays natively,
members in the order built). An answer that does not match its model is the server's bug: it is logged and answered
500, never sent.

Validation sees a 1-D numeric numpy array as a list of its dtype: every element has that dtype, so one
element stands for all of them (a 64 s answer's four 65,536-sample arrays cost microseconds, not the
tenths of a second an element-by-element check of the arrays takes). Any other array is checked in full.
"""
from __future__ import annotations

import logging
from functools import lru_cache

import numpy as np
from pydantic import BaseModel, TypeAdapter, ValidationError

from .problems import ProblemError
from .responses import JSONBytesResponse

log = logging.getLogger("gpnarx.service")


def _shape(obj):
    """``obj`` with each 1-D numeric array replaced by a list of at most its first element (see the module doc)."""
    if isinstance(obj, np.ndarray):
        if obj.ndim == 1 and obj.dtype.kind in "fiub":
            return obj[:1].tolist()
        return obj.tolist()
    if isinstance(obj, dict):
        return {k: _shape(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_shape(v) for v in obj]
    return obj


@lru_cache(maxsize=None)
def _adapter(model) -> TypeAdapter:
    return TypeAdapter(model)


def validate(model, body) -> None:
    """Check ``body`` (a dict of JSON values and numpy arrays) against ``model`` (a pydantic model or type);
    a ``ProblemError`` 500 (logged with the mismatch) when it does not match."""
    try:
        if isinstance(model, type) and issubclass(model, BaseModel):
            model.model_validate(_shape(body))
        else:
            _adapter(model).validate_python(_shape(body))
    except ValidationError as exc:
        name = getattr(model, "__name__", str(model))
        log.error("an answer does not match its response model %s: %s", name, exc)
        raise ProblemError(500, f"internal error: the answer does not match its documented schema ({name}); "
                                f"the error was logged") from None


def route_model(request):
    """The response model of the route serving ``request`` (None: the route declares none)."""
    route = request.scope.get("route")
    return getattr(route, "response_model", None)


def answer(request, body, *, headers: dict | None = None, status_code: int = 200) -> JSONBytesResponse:
    """``body`` as the JSON answer of ``request``'s route, validated by the route's response model."""
    checked(request, body)
    return JSONBytesResponse(body, status_code=status_code, headers=headers)


def checked(request, body):
    """``body`` once validated by the response model of ``request``'s route (as it is)."""
    model = route_model(request)
    if model is not None:
        validate(model, body)
    return body


__all__ = ["answer", "checked", "route_model", "validate"]
