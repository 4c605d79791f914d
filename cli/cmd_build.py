"""``gpnarx build-defaults [--registry DIR] [--only NAME[,NAME]] [--mc N]``: build the embedded default
bundles now (the missing ones, lightest first; ``--only`` or ``$GPNARX_DEFAULTS`` name a subset).

Progress lines go to stderr (the bar only without ``--json``). ``gpnarx serve`` without
``--registry`` runs ``build-defaults --only NAME --json`` in a child process per missing bundle.

Imports of the model and training packages sit inside the functions that use them: every command module is
imported to build the parser (``gpnarx.cli.main``), so each command loads only what it runs.
"""
from __future__ import annotations

import sys


def add_parser(sub):
    p = sub.add_parser("build-defaults", help="build the default registry (Bouc-Wen, BERT stand-in, real BERT)")
    p.add_argument("--registry", default=None,
                   help="registry folder (default: $GPNARX_REGISTRY or ~/.cache/gpnarx/registry)")
    p.add_argument("--only", default=None, metavar="NAME[,NAME]",
                   help="build only these defaults (default: $GPNARX_DEFAULTS or all)")
    p.add_argument("--mc", type=int, default=128, help="Monte Carlo paths of the verification report")
    p.set_defaults(func=run)


def run(args):
    # start-up: imported when the command runs (see gpnarx.cli)
    import os

    from gpnarx.cli.errors import CLIError
    from gpnarx.storage.registry import Registry
    from gpnarx.storage.remote import as_local
    from gpnarx.training.defaults import default_names, ensure_default_registry

    target = args.registry or os.environ.get("GPNARX_REGISTRY")
    if target and as_local(target) is None:
        raise CLIError(f"build-defaults builds a local folder; to put the defaults on {target}, run "
                       f"'gpnarx train NAME --registry {target}' for each (bouc-wen, bert-standin, ...)")

    names = default_names(args.only) if args.only is not None else None
    root = ensure_default_registry(args.registry, progress=not args.json, names=names, mc_paths=args.mc,
                                   log=lambda m: print(f"[gpnarx] {m}", file=sys.stderr, flush=True))
    reg = Registry(root).scan()
    return {"registry": str(root), "models": {n: reg.versions(n) for n in reg.names()}, "refused": reg.refused}
