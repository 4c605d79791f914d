"""``gpnarx serve`` and ``gpnarx export-openapi``.

::

    gpnarx serve [--registry DIR] [--host 127.0.0.1] [--port 8000] [--workers N] [--queue N]
                 [--log-level info] [--build-jobs N]
    gpnarx export-openapi [--out openapi/openapi.json]

``serve`` runs the HTTP service (``service.app``) with uvicorn over a registry: a folder or an
fsspec URL (``s3://bucket/prefix``, ``gs://...``, ``file://...``; ``$GPNARX_REGISTRY`` as well). It
rescans the registry every ``$GPNARX_REGISTRY_POLL`` seconds (default 30, 0 = off), so replicas
on one registry pick up new versions by themselves, and keeps at most ``$GPNARX_MAX_LOADED`` models
built in memory (``service.settings``). Without
``--registry`` the default registry is used (``$GPNARX_REGISTRY`` or ~/.cache/gpnarx/registry):
the port opens at once and the missing default bundles (``$GPNARX_DEFAULTS`` limits them) are
built in the background, lightest first, as many at once as there are cores (``--build-jobs``), each
loaded as soon as it is written (``cli.startup``); ``/health/ready`` lists them under ``startup``. Bounds
and the optional API key come from ``GPNARX_*`` environment variables (``service.settings``);
``--workers``/``--queue`` override GPNARX_WORKERS/GPNARX_QUEUE_SIZE. SIGHUP rescans the registry (like
``POST /v1/admin/reload``).
SIGTERM stops accepting connections and lets running requests finish for ``$GPNARX_DRAIN_TIMEOUT``
seconds (default ``GPNARX_REQUEST_TIMEOUT`` + 10 s); a request still running then is answered 503
with ``Retry-After``. Slow or idle clients are cut: ``$GPNARX_HEADER_TIMEOUT``, ``$GPNARX_BODY_TIMEOUT``,
``$GPNARX_KEEP_ALIVE_TIMEOUT``, ``$GPNARX_MAX_CONNECTIONS``, ``$GPNARX_MAX_HEADER_BYTES`` (``service.server``).

``export-openapi`` writes the OpenAPI document (sorted keys, indent 2) of the app with default
settings; ``--out -`` prints it.

Imports of the model and training packages sit inside the functions that use them: every command module is
imported to build the parser (``gpnarx.cli.main``), so each command loads only what it runs.
"""
from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

from gpnarx.cli.errors import CLIError, UsageError
from gpnarx.storage.atomicio import write_atomic

DEFAULT_OPENAPI = os.path.join("openapi", "openapi.json")

log = logging.getLogger("gpnarx.serve")


def add_parser(sub):
    p = sub.add_parser("serve", help="run the HTTP service over a model registry")
    p.add_argument("--registry", default=None,
                   help="registry folder or fsspec URL such as s3://bucket/prefix (default: $GPNARX_REGISTRY, else "
                        "the default registry, built on first use)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="TCP port (default 8000)")
    p.add_argument("--workers", type=int, default=None, help="prediction worker threads (GPNARX_WORKERS)")
    p.add_argument("--queue", type=int, default=None, help="jobs allowed to wait for a worker (GPNARX_QUEUE_SIZE)")
    p.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    p.add_argument("--build-jobs", type=int, default=None, metavar="N",
                   help="default bundles built at once on an empty default registry (default: the available "
                        "cores, at most 4)")
    p.set_defaults(func=run_serve)

    q = sub.add_parser("export-openapi", help="write the service's OpenAPI document")
    q.add_argument("--out", default=DEFAULT_OPENAPI, help=f"output file (default {DEFAULT_OPENAPI}; '-' for stdout)")
    q.set_defaults(func=run_export)


def _registry(arg) -> tuple[Path | str, dict | None]:
    """The registry (a folder, or an object-store URL as given) and, for the default registry, the
    default-build plan (``training.defaults.plan_defaults``: present, missing and skipped names)."""
    from gpnarx.storage.remote import as_local, is_url

    env = os.environ.get("GPNARX_REGISTRY", "")
    if not arg and is_url(env):  # an object store is served as it is: no default build into it
        arg = env
    if arg:
        root = as_local(arg)
        if root is None:
            return arg, None
        if not root.is_dir():
            raise CLIError(f"--registry {arg}: no such folder")
        return root, None
    # start-up: the default-registry planner (the training package) only without --registry (see gpnarx.cli);
    # a build without it still serves a given registry and says so in one line otherwise
    try:
        from gpnarx.training.defaults import default_registry_dir, plan_defaults
    except ImportError as exc:
        raise CLIError(f"no --registry given and the default registry builder is not available ({exc}); give "
                       f"--registry, or install the extra train: pip install 'gpnarx[train]'") from None
    root = default_registry_dir()
    root.mkdir(parents=True, exist_ok=True)
    return root, plan_defaults(root)


def _log(msg: str) -> None:
    log.info(msg)


def _builder(root: Path, plan: dict, jobs: int | None = None):
    """The background builder of the missing defaults (``cli.startup``), ``jobs`` builds at a time (default
    ``build_jobs``: the available cores); started by run_serve."""
    from gpnarx.cli.startup import ChildBuild, DefaultBuilder, available_cores, build_jobs
    from gpnarx.training.defaults import DERIVED

    jobs = jobs or build_jobs(len(plan["missing"]))
    threads = max(1, available_cores() // jobs) if jobs > 1 else None
    return DefaultBuilder(plan["missing"], ChildBuild(root, log=log.info, threads=threads),
                          present=plan["present"], skipped=plan["skipped"], log=_log, jobs=jobs, depends=DERIVED)


def _loader(state):
    """``on_built(name)``: rescan the app's registry; fail when the new bundle did not load."""
    def on_built(name: str) -> None:
        state.reload_from_thread()
        if name not in state.registry.bundles:
            why = [r["reason"] for r in state.refused() if r["path"].split("/")[0] == name]
            raise RuntimeError(f"{name} was written but not loaded: {why[0] if why else 'not in the registry'}")
    return on_built


def run_serve(args):
    if not 0 < args.port < 65536:
        raise UsageError(f"--port must be between 1 and 65535, got {args.port}")
    if args.build_jobs is not None and args.build_jobs < 1:
        raise UsageError(f"--build-jobs must be at least 1, got {args.build_jobs}")
    # start-up: the server and the app (FastAPI) only when serving (see gpnarx.cli)
    import uvicorn

    from gpnarx.service.app import create_app
    from gpnarx.service.observability import configure_logging, logging_config
    from gpnarx.service.server import uvicorn_options
    from gpnarx.service.settings import Settings

    root, plan = _registry(args.registry)
    try:
        settings = Settings.from_env(workers=args.workers, queue_size=args.queue, registry=str(root),
                                     sighup_reload=True)
    except (TypeError, ValueError) as exc:
        raise CLIError(str(exc)) from None
    builder = _builder(root, plan, args.build_jobs) if plan is not None else None
    try:
        app = create_app(root, settings, startup_status=builder.status if builder is not None else None)
    except OSError as exc:  # e.g. an object-store URL whose package is not installed
        raise CLIError(str(exc)) from None
    # GPNARX_LOG_FORMAT: text or json lines on stderr; set once the app exists (a failed start stays one
    # plain error line and leaves the caller's logging as it was)
    configure_logging(settings.log_format, args.log_level)
    state = app.state.service
    if state.registry_error:
        log.error("the registry could not be read (retried every poll): %s", state.registry_error)
    n = state.n_bundles()
    log.info("serving %d bundle(s) from %s on http://%s:%d (%d refused; API key %s)", n, root, args.host, args.port,
             len(state.registry.refused), "on" if settings.api_key else "off")
    for r in state.refused():
        log.warning("refused %s: %s", r["path"], r["reason"])
    if builder is not None:
        for name, why in plan["skipped"].items():
            _log(f"{why}: skipping {name}")
        if plan["missing"]:
            _log(f"building default bundle(s) {', '.join(plan['missing'])} into {root} in the background "
                 f"(first use only; /health/ready lists them under 'startup')")
        builder.on_built = _loader(state)
        builder.start()
    try:
        # drain: running requests get GPNARX_DRAIN_TIMEOUT s after SIGTERM (default GPNARX_REQUEST_TIMEOUT + 10 s);
        # one still running then is answered 503 + Retry-After (service.middleware)
        # and read deadlines, a connection limit and the request-head size (service.server)
        uvicorn.run(app, host=args.host, port=args.port, log_level=args.log_level,
                    log_config=logging_config(settings.log_format, args.log_level), **uvicorn_options(settings))
    finally:
        if builder is not None:
            builder.stop()


def run_export(args):
    # start-up: imported when the command runs (see gpnarx.cli)
    from gpnarx.service.app import openapi_json

    text = openapi_json()
    if args.out == "-":
        sys.stdout.write(text)
        return None
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(out, text)
    return {"path": str(out), "bytes": len(text.encode())}
