"""``gpnarx alias set|rm|list``: model aliases (``production``, ...) kept in the registry.

::

    gpnarx alias set  [--registry R] NAME ALIAS VERSION   point ALIAS at VERSION (a version, latest or an alias)
    gpnarx alias rm   [--registry R] NAME ALIAS           remove ALIAS
    gpnarx alias list [--registry R] [NAME]               every model's aliases (latest included)

The aliases of a model are ``REGISTRY/NAME/aliases.json``, replaced in one atomic write (a local
temporary file renamed into place; on object storage one PUT). ``latest`` is implicit: the newest
version served. A client pins a model with ``NAME:ALIAS`` (CLI ``--model``) or ALIAS as the version
(HTTP path, batch ``version``); servers see a moved alias at their next registry poll
(``GPNARX_REGISTRY_POLL``) or reload. ``set`` checks that VERSION is served (verified) first and
stores the version number it resolves to. Two operators setting aliases of one model at the same
moment: the last write wins whole (each write carries the full set it read).

Imports of the model and training packages sit inside the functions that use them: every command module is
imported to build the parser (``gpnarx.cli.main``), so each command loads only what it runs.
"""
from __future__ import annotations

import os

from gpnarx.cli.errors import CLIError, UsageError


def add_parser(sub):
    p = sub.add_parser("alias", help="set, remove or list model aliases (production, ...) in a registry")
    asub = p.add_subparsers(dest="alias_command", metavar="ACTION")
    reg_help = "registry folder or fsspec URL (default: $GPNARX_REGISTRY)"
    s = asub.add_parser("set", help="point ALIAS of model NAME at VERSION")
    s.add_argument("--registry", default=None, help=reg_help)
    s.add_argument("name", help="model name")
    s.add_argument("alias", help="alias (letters, digits, '_', '-', starting with a letter; not 'latest')")
    s.add_argument("version", help="version number, or an alias (latest, ...) resolved now")
    s.set_defaults(func=run_set)
    r = asub.add_parser("rm", help="remove ALIAS of model NAME")
    r.add_argument("--registry", default=None, help=reg_help)
    r.add_argument("name", help="model name")
    r.add_argument("alias", help="alias to remove")
    r.set_defaults(func=run_rm)
    ls = asub.add_parser("list", help="list aliases (latest included)")
    ls.add_argument("--registry", default=None, help=reg_help)
    ls.add_argument("name", nargs="?", default=None, help="one model (default: every model)")
    ls.set_defaults(func=run_list)
    p.set_defaults(func=lambda args: (_ for _ in ()).throw(CLIError("choose an action: set, rm or list")))


def _registry(args) -> str:
    reg = args.registry or os.environ.get("GPNARX_REGISTRY")
    if not reg:
        raise UsageError("--registry is required (or set GPNARX_REGISTRY)")
    return reg


def _scan(reg: str, name: str | None):
    from gpnarx.storage.bundle import BundleError
    from gpnarx.storage.registry import Registry

    try:
        return Registry(reg, lazy=True).scan(only=name)
    except BundleError as exc:
        raise CLIError(str(exc)) from None


def _current(reg: str, name: str) -> dict:
    from gpnarx.storage.bundle import BundleError
    from gpnarx.storage.registry import read_aliases

    try:
        return read_aliases(reg, name)
    except BundleError as exc:
        raise CLIError(f"{exc}; fix or remove that file first") from None


def run_set(args):
    from gpnarx.storage.bundle import BundleError, check_name
    from gpnarx.storage.registry import IMPLICIT_ALIASES, check_alias, check_version_ref, write_aliases

    reg = _registry(args)
    try:
        check_name(args.name)
        check_alias(args.alias)
        check_version_ref(args.version)
    except BundleError as exc:
        raise UsageError(str(exc)) from None
    if args.alias in IMPLICIT_ALIASES:
        raise UsageError(f"alias {args.alias!r} is implicit (the newest version) and cannot be set")
    registry = _scan(reg, args.name)
    try:
        version = registry.resolve(args.name, args.version)
    except KeyError as exc:
        raise CLIError(exc.args[0]) from None
    aliases = _current(reg, args.name)
    previous = aliases.get(args.alias)
    aliases[args.alias] = version
    write_aliases(reg, args.name, aliases)
    return {"name": args.name, "alias": args.alias, "version": version, "previous": previous}


def run_rm(args):
    from gpnarx.storage.bundle import BundleError, check_name
    from gpnarx.storage.registry import check_alias, write_aliases

    reg = _registry(args)
    try:
        check_name(args.name)
        check_alias(args.alias)
    except BundleError as exc:
        raise UsageError(str(exc)) from None
    aliases = _current(reg, args.name)
    if args.alias not in aliases:
        raise CLIError(f"alias {args.alias!r} of model {args.name!r} is not set"
                       f"{'; set: ' + ', '.join(sorted(aliases)) if aliases else ''}")
    previous = aliases.pop(args.alias)
    write_aliases(reg, args.name, aliases)
    return {"name": args.name, "alias": args.alias, "removed": True, "previous": previous}


def run_list(args):
    from gpnarx.storage.bundle import BundleError, check_name

    reg = _registry(args)
    if args.name is not None:
        try:
            check_name(args.name)
        except BundleError as exc:
            raise UsageError(str(exc)) from None
    registry = _scan(reg, args.name)
    if args.name is not None and args.name not in registry.bundles:
        raise CLIError(f"model {args.name!r} not found in {registry.root}")
    aliases = {n: registry.aliases_of(n) for n in registry.names()}
    # set aliases whose version is not served (removed or refused): listed apart, so they can be moved
    dangling = {n: {a: v for a, v in sorted(registry.aliases.get(n, {}).items()) if a not in aliases.get(n, {})}
                for n in registry.aliases}
    return {"aliases": aliases, "dangling": {n: d for n, d in dangling.items() if d}}
