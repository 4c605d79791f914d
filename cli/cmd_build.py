"""``gpnarx build-defaults [--registry DIR]``: build the embedded default bundles now."""
from __future__ import annotations


def add_parser(sub):
    p = sub.add_parser("build-defaults", help="build the default registry (Bouc-Wen, BERT stand-in, real BERT)")
    p.add_argument("--registry", default=None,
                   help="registry folder (default: $GPNARX_REGISTRY or ~/.cache/gpnarx/registry)")
    p.add_argument("--mc", type=int, default=128, help="Monte Carlo paths of the verification report")
    p.set_defaults(func=run)


def run(args):
    # start-up: imported when the command runs (see gpnarx.cli)
    from gpnarx.model.bundle import Registry
    from gpnarx.training.defaults import ensure_default_registry

    root = ensure_default_registry(args.registry, progress=not args.json, mc_paths=args.mc)
    reg = Registry(root).scan()
    return {"registry": str(root), "models": {n: reg.versions(n) for n in reg.names()}, "refused": reg.refused}
