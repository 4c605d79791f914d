"""Which array backend runs the free run: ``numpy`` (the default, always there) or ``jax`` (optional).

``jax`` runs the free run as one compiled program (``model.freerun.jax_backend``) on whatever device JAX
sees: a GPU when the CUDA build of jaxlib is installed, else the CPU. It is installed by the
extra ``pip install 'gpnarx[jax]'`` (CPU); docs/accelerator.md says how to add the CUDA build.

The default comes from the environment variable ``GPNARX_BACKEND`` (the service's default too);
a call, a CLI ``--backend`` or an HTTP body's ``"backend"`` overrides it.
"""
from __future__ import annotations

import os

BACKENDS = ("numpy", "jax")
ENV_VAR = "GPNARX_BACKEND"


class BackendUnavailable(ValueError):
    """The backend asked for is not installed here (the message says how to install it)."""


def check_backend(name, field: str = "backend") -> str:
    """``name`` validated: one of ``BACKENDS`` (None: the default, ``default_backend()``)."""
    if name is None:
        return default_backend()
    if not isinstance(name, str) or name.lower() not in BACKENDS:
        raise ValueError(f"{field} must be one of {list(BACKENDS)}, got {name!r}")
    return name.lower()


def default_backend() -> str:
    """``GPNARX_BACKEND`` when set (validated), else ``numpy``."""
    raw = os.environ.get(ENV_VAR, "").strip()
    return check_backend(raw, ENV_VAR) if raw else "numpy"


def jax_available() -> bool:
    try:
        import jax  # noqa: F401
    except ImportError:
        return False
    return True


def require_jax():
    """The ``jax`` module with 64-bit arrays enabled, or ``BackendUnavailable`` saying how to install it."""
    try:
        import jax
    except ImportError:
        raise BackendUnavailable("backend 'jax' is not installed here: pip install 'gpnarx[jax]' "
                                 "(docs/accelerator.md adds the CUDA build for a GPU)") from None
    jax.config.update("jax_enable_x64", True)
    return jax


def jax_device() -> str:
    """The device JAX computes on, in words (e.g. 'gpu: NVIDIA H100 80GB HBM3' or 'cpu')."""
    jax = require_jax()
    d = jax.devices()[0]
    kind = getattr(d, "device_kind", "") or ""
    return f"{d.platform}: {kind}" if d.platform != "cpu" else "cpu"
