"""Route dependencies: the app's state and settings, the API key, and the shared path parameters.

``require_api_key`` guards every /v1 router (``dependencies=[Security(require_api_key)]``); being a
security dependency, it is what puts the ``ApiKeyAuth`` scheme into the OpenAPI document.
"""
from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request, Security
from fastapi import Path as PathParam
from fastapi.security import APIKeyHeader

from .problems import ProblemError
from .schemas import NAME_PATTERN, VERSION_PATTERN
from .settings import Settings
from .state import ServiceState

API_KEY_HEADER = "X-API-Key"


def get_state(request: Request) -> ServiceState:
    """The ``ServiceState`` of the app serving ``request``."""
    return request.app.state.service


def get_settings(request: Request) -> Settings:
    return request.app.state.service.settings


StateDep = Annotated[ServiceState, Depends(get_state)]
SettingsDep = Annotated[Settings, Depends(get_settings)]

api_key_header = APIKeyHeader(name=API_KEY_HEADER, scheme_name="ApiKeyAuth", auto_error=False,
                              description="Required on /v1 routes only when the server sets GPNARX_API_KEY.")


def key_problem(key: str | None, given: str | None) -> ProblemError | None:
    """The 401 problem unless ``key`` is unset or ``given`` holds it (compared in constant time)."""
    if not key:
        return None
    if not given or not hmac.compare_digest(given.encode("utf-8", "replace"), key.encode("utf-8")):
        return ProblemError(401, f"a valid API key is required in the {API_KEY_HEADER} header", API_KEY_HEADER,
                            headers={"WWW-Authenticate": f'ApiKey header="{API_KEY_HEADER}"'})
    return None


async def require_api_key(state: StateDep, given: Annotated[str | None, Security(api_key_header)] = None) -> None:
    """401 unless the server sets no key (``GPNARX_API_KEY``) or ``X-API-Key`` holds it.

    ``service.middleware.GuardMiddleware`` checks the same before any body byte is read; this
    dependency documents the scheme in OpenAPI and guards a route mounted outside /v1 by mistake."""
    problem = key_problem(state.settings.api_key, given)
    if problem is not None:
        raise problem


#: dependencies of every /v1 router
V1 = [Security(require_api_key)]

#: path parameters shared by the routers
NameP = Annotated[str, PathParam(description="Model name (1-64 of letters, digits, '_', '-', '.').",
                                 pattern=NAME_PATTERN, max_length=64)]
VersionP = Annotated[str, PathParam(description="Model version (a positive integer) or alias (`latest`, or one an "
                                                "operator set with `gpnarx alias set`, e.g. `production`).",
                                    pattern=VERSION_PATTERN)]

RECORD_PROBLEMS = {400: "Body is not JSON", 401: "API key missing or wrong (when GPNARX_API_KEY is set)",
                   404: "Unknown model or version", 413: "Record, Monte Carlo work or body too large",
                   422: "Invalid request (field named in `field`)", 503: "Busy: retry after Retry-After seconds",
                   504: "The request exceeded its time limit (GPNARX_REQUEST_TIMEOUT) while computing"}

