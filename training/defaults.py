"""The embedded default registry: built on first use from the shipped configs.

``ensure_default_registry()`` returns the registry folder (``$GPNARX_REGISTRY`` or
``~/.cache/gpnarx/registry``), training any missing default bundle first: Bouc-Wen, the BERT
stand-in and its bolt-loosening monitor (9 Hz sine probe, novelty calibrated) always, the real BERT
bundle and its real-rig monitor (``training.real_monitor``: the same GP with a novelty calibration
from healthy real windows, derived without a refit) too when the lab records are present
(``$GPNARX_BERT_DATA`` or ``../shared/data/bert-t5nm`` beside the repository).
``$GPNARX_DEFAULTS`` (comma-separated names, e.g. ``bouc-wen``) limits the defaults built.

``DEFAULT_BUNDLES`` is in build order, lightest first (measured: docs/benchmarks.md, "First
start"), so ``gpnarx serve`` on an empty registry has a model to serve as soon as possible. A
default build writes the same model as ``gpnarx train NAME`` but a lighter verification report
(``build_default``): fewer Monte Carlo paths (``DEFAULT_MC``) than the full protocol
(``gpnarx reproduce``), and linearised bands for the bundles without a novelty calibration
(``LIGHT_METHOD``), whose report runs take seconds instead of minutes; the monitor keeps Monte Carlo
runs because its novelty threshold is calibrated on them.
"""
from __future__ import annotations

import contextlib
import importlib.util
import os
import sys
from pathlib import Path

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None

from gpnarx.configs import CONFIG_DIR, shipped_config, shipped_config_names
from gpnarx.storage.registry import Registry
from gpnarx.training.config import bert_data_dir
from gpnarx.training.pipeline import train
from gpnarx.training.real_monitor import build_real_monitor

__all__ = ["CONFIG_DIR", "DEFAULT_BUNDLES", "DEFAULT_MC", "LIGHT_METHOD", "build_default", "build_lock",
           "default_names", "default_registry_dir", "ensure_default_registry", "lock_file", "plan_defaults",
           "shipped_config", "shipped_config_names"]

#: build order, lightest first (first start on 2 cores: docs/benchmarks.md)
DEFAULT_BUNDLES = ("bouc-wen", "bert-standin", "bert-standin-monitor", "bert-real", "bert-real-monitor")
#: defaults derived from another default (a novelty calibration, no refit) rather than trained
DERIVED = {"bert-real-monitor": "bert-real"}
#: defaults that need the real BERT records
NEEDS_BERT_DATA = ("bert-real", "bert-real-monitor")
DEFAULT_MC = 128
#: report method of a default build; absent: the config's own (``[predict] method``)
LIGHT_METHOD = {"bouc-wen": "linear", "bert-standin": "linear"}
DEFAULTS_ENV = "GPNARX_DEFAULTS"


def default_registry_dir() -> Path:
    env = os.environ.get("GPNARX_REGISTRY")
    if env:
        return Path(env).expanduser()
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "gpnarx" / "registry"


def default_names(spec: str | None = None) -> tuple[str, ...]:
    """The defaults to build, lightest first: all, or those named in ``spec`` / ``$GPNARX_DEFAULTS``."""
    if spec is None:
        spec = os.environ.get(DEFAULTS_ENV, "")
    wanted = [s.strip() for s in spec.split(",") if s.strip()]
    if not wanted:
        return DEFAULT_BUNDLES
    unknown = [w for w in wanted if w not in DEFAULT_BUNDLES]
    if unknown:
        raise ValueError(f"{DEFAULTS_ENV}: unknown default bundle {unknown[0]!r}; choose among "
                         f"{', '.join(DEFAULT_BUNDLES)}")
    return tuple(n for n in DEFAULT_BUNDLES if n in wanted)


def _bert_data_present() -> bool:
    d = bert_data_dir()
    return (d / "Sine").is_dir()


def plan_defaults(root, names=None) -> dict:
    """What a default build of ``root`` has to do: ``present``, ``missing`` (in build order) and
    ``skipped`` ({name: reason}) default names."""
    names = default_names() if names is None else tuple(names)
    root = Path(root)
    have = Registry(root).scan().bundles if root.is_dir() else {}
    plan = {"present": [], "missing": [], "skipped": {}}
    for name in names:
        if name in have:
            plan["present"].append(name)
        elif name in NEEDS_BERT_DATA and not _bert_data_present():
            plan["skipped"][name] = "real BERT records not found ($GPNARX_BERT_DATA or ../shared/data/bert-t5nm)"
        elif name in DERIVED and DERIVED[name] not in have and DERIVED[name] not in plan["missing"]:
            plan["skipped"][name] = f"derived from {DERIVED[name]}, which is neither present nor being built"
        else:
            plan["missing"].append(name)
    return plan


def build_default(name: str, root, progress: bool = False, log=None, mc_paths: int = DEFAULT_MC) -> dict:
    """Train the default bundle ``name`` into ``root`` (the shipped config, lighter report)."""
    if name not in DEFAULT_BUNDLES:
        raise ValueError(f"{name!r} is not a default bundle; choose among {', '.join(DEFAULT_BUNDLES)}")
    if name in DERIVED:
        return build_real_monitor(Path(root), bert_data_dir(), mc_paths=mc_paths, log=log)
    # the core install (no extra train) builds and serves the defaults too, their reports without figures
    if importlib.util.find_spec("matplotlib") is None and log:
        log(f"{name}: matplotlib is not installed (extra train): the training report is written without figures "
            f"(pip install 'gpnarx[train]', then gpnarx train {name} --registry REGISTRY for a version with them)")
    return train(shipped_config(name), Path(root), progress=progress, mc_paths=mc_paths, log=log,
                 report_method=LIGHT_METHOD.get(name), report=True)


def ensure_default_registry(path=None, progress: bool = True, names=None, mc_paths: int = DEFAULT_MC,
                            log=None) -> Path:
    """Build the missing default bundles into ``path`` (default registry) and return it.

    ``names``: the defaults to build (default: ``default_names()``); ``log``: a callable taking one
    line (default: stderr when ``progress``).
    """
    root = Path(path) if path else default_registry_dir()
    root.mkdir(parents=True, exist_ok=True)
    if log is None and progress:
        log = lambda m: print(f"[gpnarx] {m}", file=sys.stderr, flush=True)  # noqa: E731
    plan = plan_defaults(root, names)
    for name, why in plan["skipped"].items():
        if log:
            log(f"{why}: skipping {name}")
    for name in plan["missing"]:
        with build_lock(root, log, name):
            # under the lock: another process (a server's parallel builds, build-defaults) may have built it
            if name in plan_defaults(root, [name])["present"]:
                continue
            if log:
                log(f"building default bundle {name} into {root} (first use only)")
            build_default(name, root, progress=progress, log=log, mc_paths=mc_paths)
    return root


def lock_file(name: str) -> str:
    """The lock file of default ``name``'s build, in the registry root (the scan ignores files there)."""
    return f".defaults-{name}.lock"


@contextlib.contextmanager
def build_lock(root: Path, log=None, name: str = "defaults"):
    """Hold ``ROOT/.defaults-NAME.lock`` (an exclusive ``flock``) while default ``name`` is built, so two
    processes starting on the same empty registry (two ``gpnarx serve``, or a server and a
    ``build-defaults``) build each default once: the second waits, then finds the bundle present. One
    lock per default, so different defaults build at the same time (``gpnarx serve`` builds them in
    parallel, ``cli.startup``). The lock is the kernel's, released when its holder exits, even killed.
    Without ``fcntl`` (not POSIX) the build runs unlocked."""
    if fcntl is None:  # pragma: no cover - POSIX is where the service runs
        yield
        return
    with open(Path(root) / lock_file(name), "a+") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            if log:
                log(f"another process is building {name} into {root}: waiting for it")
            fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)
