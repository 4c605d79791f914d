"""GP-NARX surrogate of hysteretic bolted structures (Teloli et al., MSSP 159 (2021) 107751).

Subpackages: ``gpnarx.model`` (the surrogate, numpy/scipy only), ``gpnarx.storage`` (bundles, the
registry, record files), ``gpnarx.training`` (offline work:
records, simulators, configs, lag surface, training pipeline), ``gpnarx.service`` (the FastAPI app)
and ``gpnarx.cli`` (the ``gpnarx`` console script).
"""
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("gpnarx")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0+unknown"
