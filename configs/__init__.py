"""The dataset configs shipped with the package (``*.toml`` package data), found by name.

``gpnarx train NAME`` and the default registry use them; ``shipped_config("bouc-wen")`` is the path of
``bouc-wen.toml`` wherever the package is installed.
"""
from __future__ import annotations

from importlib import resources
from pathlib import Path

CONFIG_DIR = Path(str(resources.files(__name__)))


def shipped_config_names() -> list[str]:
    """Names of the configs shipped with the package (``gpnarx train NAME`` accepts them)."""
    return sorted(p.stem for p in CONFIG_DIR.glob("*.toml"))


def shipped_config(name: str) -> Path:
    """The path of the shipped config ``NAME.toml``; FileNotFoundError naming the shipped ones otherwise."""
    p = CONFIG_DIR / f"{name}.toml"
    if not p.is_file():
        raise FileNotFoundError(f"no shipped config named {name!r}; shipped: {', '.join(shipped_config_names())}")
    return p
