"""Service settings and request bounds: ``Settings``, one field per environment variable ``GPNARX_<FIELD>``.

pydantic-settings reads each field from its variable (arguments win; ``Settings.from_env(environ)`` reads a given
mapping, ``{}`` for the defaults alone). The fields' metadata (label, what exceeding the bound answers) is the one
list of the service's bounds: the OpenAPI description (``DEFAULT_BOUNDS``, the committed document's defaults) and
the table in docs/api.md (``settings_table()``, checked by tests/test_settings.py) are generated from it; docs/api.md
says what each setting does and how to choose them together.
"""
from __future__ import annotations

import math
import os
from contextvars import ContextVar
from typing import Any, Literal

from pydantic import Field, ValidationError, model_validator
from pydantic.fields import FieldInfo
from pydantic_settings import BaseSettings, EnvSettingsSource, SettingsConfigDict, SettingsError
from pydantic_settings.sources.utils import parse_env_vars

from gpnarx.operations import MC_PATHS_MAX
from gpnarx.runtime import DEFAULT_BLAS_THREADS, DEFAULT_MMAP_THRESHOLD, env_int

MiB = 1024 * 1024
CONFIRM_WINDOW = 300.0  # [s] polls a held registry listing needs by default (registry_confirm_scans)
DRAIN_MARGIN = 10.0  # [s] the default drain window's margin over GPNARX_REQUEST_TIMEOUT
ENV_PREFIX = "GPNARX_"


def _default_workers() -> int:
    return max(1, min(4, os.cpu_count() or 1))


def _setting(default: Any = None, *, label: str, exceeded: str = "-", shown: str | None = None, kind: str,
             bound: bool = False, default_factory=None, **constraints) -> Any:
    """A settings field with the metadata of the limits table (``settings_table``)."""
    extra = {"label": label, "exceeded": exceeded, "shown": shown, "kind": kind, "bound": bound}
    if default_factory is not None:
        return Field(default_factory=default_factory, description=label, json_schema_extra=extra, **constraints)
    return Field(default, description=label, json_schema_extra=extra, **constraints)


_POSITIVE = "a positive integer"
_NON_NEGATIVE = "a non-negative integer"
_SECONDS = "a non-negative number of seconds"
_SHARE = "a number from 0 to 1"
_BOOL = "true or false"
_TRUE, _FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")

#: the mapping ``Settings.from_env`` was given (None: ``os.environ``)
_ENVIRON: ContextVar[Any] = ContextVar("gpnarx_settings_environ", default=None)


def _parse_env(var: str, kind: str | None, raw: str) -> Any:
    """The value of variable ``var`` for a field of ``kind`` (text as it is); ``ValueError`` naming the variable."""
    if kind is None:  # text: api_key, registry, the Literal choices (the field checks them)
        return raw
    if kind == _BOOL:
        if raw.strip().lower() not in _TRUE + _FALSE:
            raise ValueError(f"environment variable {var} must be {kind}, got {raw!r}")
        return raw.strip().lower() in _TRUE
    if kind in (_SECONDS, _SHARE):
        try:
            return float(raw)
        except ValueError:
            raise ValueError(f"environment variable {var} must be {kind}, got {raw!r}") from None
    return env_int(var, None, {var: raw}, minimum=None)  # the package's integer parser; the field checks the range


class _EnvSource(EnvSettingsSource):
    """pydantic-settings' environment source (``GPNARX_<FIELD>``, ``model_config``'s prefix; a blank value is
    unset) over ``os.environ``, or the mapping ``Settings.from_env`` was given; each value is parsed to its
    field's kind, so a strict field takes ``"7"`` as 7 and a bad value names its variable."""

    def _load_env_vars(self):
        env = _ENVIRON.get()
        return parse_env_vars(os.environ if env is None else env, self.case_sensitive, self.env_ignore_empty,
                              self.env_parse_none_str)

    def prepare_field_value(self, field_name: str, field: FieldInfo, value: Any, value_is_complex: bool) -> Any:
        if value is None or field_name not in ENV:  # sighup_reload is no environment setting
            return None
        return _parse_env(env_var(field_name), (field.json_schema_extra or {}).get("kind"), value)


class Settings(BaseSettings):
    """Runtime configuration of the HTTP service (``settings_table()`` lists it)."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, env_ignore_empty=True, frozen=True, strict=True,
                                      extra="forbid", validate_default=True)

    max_samples: int = _setting(65536, ge=1, kind=_POSITIVE, bound=True, label="samples per record",
                                exceeded="413, field `u` (or `y`)")
    max_batch: int = _setting(64, ge=1, kind=_POSITIVE, bound=True, label="records per batch",
                              exceeded="413, field `requests`")
    mc_paths_default: int | None = _setting(None, ge=1, kind=_POSITIVE, bound=True, shown="the model's",
                                            label="Monte Carlo paths when a request names none (unset: the "
                                                  "model's config `[predict] mc_paths`, as the CLI uses)")
    mc_paths_max: int = _setting(MC_PATHS_MAX, ge=1, kind=_POSITIVE, bound=True, label="Monte Carlo paths per record",
                                 exceeded="422, field `mc_paths`")
    max_mc_work: int = _setting(2**24, ge=1, kind=_POSITIVE, bound=True, shown="2^24",
                                label="path-steps (paths x samples) per HTTP request (a batch shares it)",
                                exceeded="413, field `mc_paths`")
    max_body_bytes: int = _setting(32 * MiB, ge=1, kind=_POSITIVE, bound=True, shown="32 MiB", label="body size",
                                   exceeded="413, field `body`")
    workers: int = _setting(default_factory=_default_workers, ge=1, kind=_POSITIVE, shown="min(4, CPUs)",
                            label="worker threads running compute jobs")
    queue_size: int = _setting(16, ge=0, kind=_NON_NEGATIVE, label="jobs waiting for a worker",
                               exceeded="503 + `Retry-After`")
    retry_after: int = _setting(2, ge=1, kind=_POSITIVE, shown="2 s", label="`Retry-After` of a 503 (seconds)")
    request_timeout: float = _setting(120.0, ge=0, allow_inf_nan=False, kind=_SECONDS, shown="120 s",
                                      label="time per predict/loops/novelty/batch request, queue wait included "
                                            "(0 = none)",
                                      exceeded="504 if its job was computing, 503 + `Retry-After` if still queued")
    drain_timeout: float | None = _setting(None, ge=0, allow_inf_nan=False, kind=_SECONDS,
                                           shown="`GPNARX_REQUEST_TIMEOUT` + 10 s (130 s)",
                                           label="seconds `gpnarx serve` lets running requests finish after SIGTERM "
                                                 "(deploy/k8s: `terminationGracePeriodSeconds` above it)",
                                           exceeded="503 + `Retry-After` for a request still running")
    header_timeout: float = _setting(10.0, ge=0, allow_inf_nan=False, kind=_SECONDS, shown="10 s",
                                     label="seconds a connection may take to send a request head (0 = none)",
                                     exceeded="408, connection closed")
    body_timeout: float = _setting(60.0, ge=0, allow_inf_nan=False, kind=_SECONDS, shown="60 s",
                                   label="seconds a request may take to send its body once its head is in (0 = none)",
                                   exceeded="408, field `body`, connection closed")
    keep_alive_timeout: float = _setting(5.0, ge=0, allow_inf_nan=False, kind=_SECONDS, shown="5 s",
                                         label="seconds an idle connection is kept open between requests")
    max_connections: int = _setting(256, ge=0, kind=_NON_NEGATIVE,
                                    label="open connections per server process (0 = no limit)",
                                    exceeded="503 + `Retry-After` at once, connection closed")
    max_header_bytes: int = _setting(16 * 1024, ge=1024, kind="an integer of at least 1024", shown="16 KiB",
                                     label="bytes of an incomplete request head the server buffers",
                                     exceeded="400, connection closed")
    api_key: str | None = _setting(None, kind=None, shown="unset (off)",
                                   label="API key every `/v1` route then needs in `X-API-Key`", exceeded="401")
    registry: str | None = _setting(None, kind=None, shown="unset",
                                    label="the registry: a folder or an fsspec URL (`s3://bucket/prefix`)")
    blas_threads: int = _setting(DEFAULT_BLAS_THREADS, ge=0, kind=_NON_NEGATIVE,
                                 label="BLAS threads per process (0 = leave BLAS)")
    mmap_threshold: int = _setting(DEFAULT_MMAP_THRESHOLD, ge=0, kind=_NON_NEGATIVE, shown="32 MiB",
                                   label="glibc's mmap threshold (0 = leave malloc)")
    registry_poll: float = _setting(30.0, ge=0, allow_inf_nan=False, kind=_SECONDS, shown="30 s",
                                    label="seconds between rescans of the registry (0 = none)")
    registry_drop_share: float = _setting(0.5, ge=0, le=1, allow_inf_nan=False, kind=_SHARE,
                                          label="share of the served versions one registry scan may drop; a scan "
                                                "dropping more (or every version) is held",
                                          exceeded="the last good registry keeps serving (`/health/ready` "
                                                   "`registry_held`)")
    registry_confirm_scans: int | None = _setting(None, ge=1, kind=_POSITIVE,
                                                  shown="the polls of 5 min (at least 3)",
                                                  label="consecutive scans that must show the same held listing "
                                                        "before it is served (1 = at once; `POST /v1/admin/reload?"
                                                        "accept_removal=true` serves it now)")
    registry_leftover_age: float = _setting(600.0, ge=0, allow_inf_nan=False, kind=_SECONDS, shown="600 s",
                                            label="seconds without a new object after which a server's start or scan "
                                                  "removes what a killed write left: an unpublished version on an "
                                                  "object store, a `.tmp-*` folder of another host (0 = never; a "
                                                  "folder whose writer is gone from this host goes at once)")
    max_loaded: int = _setting(8, ge=1, kind=_POSITIVE, label="built models kept in memory (least recently used "
                                                              "dropped first)")
    backend: Literal["numpy", "jax"] = _setting("numpy", kind=None, shown="numpy",
                                                label="array backend of the free run when a body names none "
                                                      "('jax': docs/accelerator.md)",
                                                exceeded="422 on a request if 'jax' is not installed")
    stream_key: str | None = _setting(None, kind=None, shown="unset (checksum only)",
                                      label="secret that signs stream state tokens (`state`, `return_state`); every "
                                            "replica of a deployment needs the same one. Unset: tokens carry a "
                                            "checksum, not a signature",
                                      exceeded="422, field `state`, for a token signed with another key")
    log_format: Literal["text", "json"] = _setting("text", kind=None, shown="text",
                                                   label="log lines of `gpnarx serve`: `text`, or `json` (one object "
                                                         "per line: time, level, logger, message, request_id)")
    audit_log: str | None = _setting(None, kind=None, shown="unset (stdout)",
                                     label="audit trail, one JSON line per novelty verdict: a file, an fsspec URL, "
                                           "`-` (stdout) or `off`",
                                     exceeded="a failed write is counted (`/metrics`, `/health/ready` `audit`); the "
                                              "answer is sent")
    audit_predicts: bool = _setting(False, kind=_BOOL, shown="false", label="also write an audit line for each predict")
    audit_queue: int = _setting(10000, ge=1, kind=_POSITIVE, label="audit lines waiting to be written",
                                exceeded="the line is dropped and counted; the answer is sent")
    drift_window: int = _setting(200, ge=1, kind=_POSITIVE,
                                 label="answers per model in the rolling window of the drift gauges on `/metrics`")
    otel: Literal["off", "console", "otlp"] = _setting("off", kind=None, shown="off",
                                                       label="OpenTelemetry tracing (extra `otel`): `off`, "
                                                             "`console` (one JSON line per span on stderr) or "
                                                             "`otlp` (OTLP/HTTP to `OTEL_EXPORTER_OTLP_ENDPOINT`)",
                                                       exceeded="the server does not start without the extra "
                                                                "(`pip install 'gpnarx[otel]'`)")
    #: reload the registry on SIGHUP (only where the event loop runs in the main thread); not an env setting
    sighup_reload: bool = False

    def __init__(self, **values: Any):
        try:
            super().__init__(**values)
        except SettingsError as exc:  # a bad environment value: its variable and what it must be
            raise ValueError(str(exc.__cause__ or exc)) from None
        except ValidationError as exc:  # one plain message naming the setting
            err = exc.errors()[0]
            name = str(err["loc"][0]) if err.get("loc") else ""
            field = type(self).model_fields.get(name)
            kind = (field.json_schema_extra or {}).get("kind") if field is not None else None
            if not name:  # a rule across settings (model validator)
                raise ValueError(str(err["msg"]).removeprefix("Value error, ")) from None
            if kind is None:
                raise ValueError(f"setting {name}: {err['msg']}") from None
            raise ValueError(f"setting {name} must be {kind}, got {err.get('input')!r}") from None

    @classmethod
    def settings_customise_sources(cls, settings_cls, init_settings, env_settings, dotenv_settings,
                                   file_secret_settings):
        return (init_settings, _EnvSource(settings_cls))  # arguments win over the environment; no .env, no secrets

    @model_validator(mode="before")
    @classmethod
    def _blank_key_is_none(cls, data: Any) -> Any:
        if isinstance(data, dict) and isinstance(data.get("api_key"), str) and not data["api_key"].strip():
            data = {**data, "api_key": None}
        if isinstance(data, dict) and isinstance(data.get("registry"), os.PathLike):  # a folder given as a Path
            data = {**data, "registry": os.fspath(data["registry"])}
        return data

    @model_validator(mode="after")
    def _paths_default_within_max(self) -> Settings:
        if self.mc_paths_default is not None and self.mc_paths_default > self.mc_paths_max:
            raise ValueError(f"setting mc_paths_default ({self.mc_paths_default}) exceeds mc_paths_max "
                             f"({self.mc_paths_max})")
        return self

    @classmethod
    def from_env(cls, environ=None, **overrides) -> Settings:
        """Settings from the ``GPNARX_*`` variables of ``environ`` (default ``os.environ``, as ``Settings()``
        reads; ``{}``: the defaults alone); ``overrides`` that are not None win."""
        token = _ENVIRON.set(os.environ if environ is None else environ)
        try:
            return cls(**{k: v for k, v in overrides.items() if v is not None})
        finally:
            _ENVIRON.reset(token)

    def with_(self, **changes) -> Settings:
        """A copy with ``changes`` (validated like the original)."""
        return type(self)(**{**self.model_dump(), **changes})

    @property
    def confirm_scans(self) -> int:
        """Consecutive scans a held registry listing needs: ``registry_confirm_scans``, else the polls
        of ``CONFIRM_WINDOW`` seconds (at least 3), so a store that is empty for a few minutes at
        most, whatever the poll interval, never empties the server."""
        if self.registry_confirm_scans is not None:
            return int(self.registry_confirm_scans)
        return max(3, math.ceil(CONFIRM_WINDOW / self.registry_poll)) if self.registry_poll > 0 else 3

    @property
    def drain_seconds(self) -> float:
        """Graceful-shutdown window [s]: ``drain_timeout``, else ``request_timeout`` + 10 s (130 s
        when requests have no time limit), so the longest request a deadline allows can finish."""
        if self.drain_timeout is not None:
            return float(self.drain_timeout)
        return (self.request_timeout if self.request_timeout > 0 else 120.0) + DRAIN_MARGIN

    @property
    def leftover_seconds(self) -> float:
        """Age [s] after which a scan removes a killed write's leftovers (``registry_leftover_age``; inf if 0)."""
        return float(self.registry_leftover_age) if self.registry_leftover_age > 0 else math.inf

    def bounds(self) -> dict:
        """The request bounds in force (no secrets)."""
        return {k: getattr(self, k) for k in DEFAULT_BOUNDS}


def env_var(name: str) -> str:
    """The environment variable of setting ``name``."""
    return ENV_PREFIX + name.upper()


def _meta(name: str) -> dict:
    return Settings.model_fields[name].json_schema_extra or {}


#: Default request bounds (the OpenAPI description and docs/api.md show them).
DEFAULT_BOUNDS = {name: f.default for name, f in Settings.model_fields.items()
                  if (f.json_schema_extra or {}).get("bound")}
#: setting -> environment variable
ENV = {name: env_var(name) for name in Settings.model_fields if name != "sighup_reload"}


def settings_table() -> str:
    """The Markdown table of every ``GPNARX_*`` setting (docs/api.md holds it; tests/test_settings.py checks)."""
    rows = ["| setting | variable | default | exceeded |", "|---|---|---|---|"]
    for name, var in ENV.items():
        f, m = Settings.model_fields[name], _meta(name)
        shown = m.get("shown") or str(f.default)
        rows.append(f"| {m['label']} | `{var}` | {shown} | {m['exceeded']} |")
    return "\n".join(rows) + "\n"


if __name__ == "__main__":  # python -m gpnarx.service.settings: print the table for docs/api.md
    print(settings_table(), end="")
