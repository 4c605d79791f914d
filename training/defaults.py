"""The embedded default registry: built on first use from the shipped configs.

``ensure_default_registry()`` returns the registry folder (``$GPNARX_REGISTRY`` or
``~/.cache/gpnarx/registry``), training any missing default bundle first: Bouc-Wen, the BERT
stand-in and its bolt-loosening monitor (9 Hz sine probe, novelty calibrated) always, the real BERT bundle too when the lab records are present
(``$GPNARX_BERT_DATA`` or ``../shared/data/bert-t5nm`` beside the repository). The default build
uses fewer Monte Carlo paths for its verification report than the full protocol
(``gpnarx reproduce``) so it finishes in a few minutes on 2 cores.
"""
from __future__ import annotations

import os
import sys
from importlib import resources
from pathlib import Path

# Shipped configs are package data of ``gpnarx.configs`` (the repository's ``configs/`` folder).
CONFIG_DIR = Path(str(resources.files("gpnarx.configs")))
DEFAULT_BUNDLES = ("bouc-wen", "bert-standin", "bert-standin-monitor", "bert-real")
DEFAULT_MC = 128


def default_registry_dir() -> Path:
    env = os.environ.get("GPNARX_REGISTRY")
    if env:
        return Path(env).expanduser()
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "gpnarx" / "registry"


def shipped_config_names() -> list[str]:
    """Names of the configs shipped with the package (``gpnarx train NAME`` accepts them)."""
    return sorted(p.stem for p in CONFIG_DIR.glob("*.toml"))


def shipped_config(name: str) -> Path:
    p = CONFIG_DIR / f"{name}.toml"
    if not p.is_file():
        raise FileNotFoundError(f"no shipped config named {name!r}; shipped: {', '.join(shipped_config_names())}")
    return p


def _bert_data_present() -> bool:
    from gpnarx.training.config import bert_data_dir

    d = bert_data_dir()
    return (d / "Sine").is_dir()


def ensure_default_registry(path=None, progress: bool = True, names=DEFAULT_BUNDLES, mc_paths: int = DEFAULT_MC) -> Path:
    """Build the missing default bundles into ``path`` (default registry) and return it."""
    from gpnarx.model.bundle import Registry
    from gpnarx.training.pipeline import train

    root = Path(path) if path else default_registry_dir()
    root.mkdir(parents=True, exist_ok=True)
    have = Registry(root).scan().bundles
    log = (lambda m: print(f"[gpnarx] {m}", file=sys.stderr)) if progress else None
    for name in names:
        if name in have:
            continue
        if name == "bert-real" and not _bert_data_present():
            if log:
                log("real BERT records not found ($GPNARX_BERT_DATA or ../shared/data/bert-t5nm): skipping bert-real")
            continue
        if log:
            log(f"building default bundle {name} into {root} (first use only)")
        train(shipped_config(name), root, progress=progress, mc_paths=mc_paths, log=log)
    return root
