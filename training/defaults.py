"""The embedded default registry: built on first use from the shipped configs.

``ensure_default_registry()`` returns the registry folder (``$GPNARX_REGISTRY`` or
``~/.cache/gpnarx/registry``), training any missing default bundle first: Bouc-Wen, the BERT
stand-in and its bolt-loosening monitor (9 Hz sine probe, novelty calibrated) always, the real
BERT bundle too when the lab records are present (``$GPNARX_BERT_DATA`` or
``../shared/data/bert-t5nm`` beside the repository). The default build uses fewer Monte Carlo
paths for its verification report than the full protocol (``gpnarx reproduce``) so it finishes in
a few minutes on 2 cores.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

from gpnarx.configs import CONFIG_DIR, shipped_config, shipped_config_names
from gpnarx.model.bundle import Registry
from gpnarx.training.config import bert_data_dir
from gpnarx.training.pipeline import train

__all__ = ["CONFIG_DIR", "DEFAULT_BUNDLES", "DEFAULT_MC", "default_registry_dir", "ensure_default_registry",
           "shipped_config", "shipped_config_names"]

DEFAULT_BUNDLES = ("bouc-wen", "bert-standin", "bert-standin-monitor", "bert-real")
DEFAULT_MC = 128


def default_registry_dir() -> Path:
    env = os.environ.get("GPNARX_REGISTRY")
    if env:
        return Path(env).expanduser()
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "gpnarx" / "registry"


def _bert_data_present() -> bool:
    d = bert_data_dir()
    return (d / "Sine").is_dir()


def ensure_default_registry(path=None, progress: bool = True, names=DEFAULT_BUNDLES,
                            mc_paths: int = DEFAULT_MC) -> Path:
    """Build the missing default bundles into ``path`` (default registry) and return it."""
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
