"""First start of ``gpnarx serve`` on the default registry: build the missing defaults in the background.

The server opens its port at once (``/health/live`` answers while bundles are built) and
``DefaultBuilder`` builds the missing default bundles in the order ``training.defaults`` gives
(lightest first), up to ``jobs`` at a time (``build_jobs()``: the cores this process may use, so on 2
cores two builds run side by side); a default derived from another (``depends``: ``bert-real-monitor``
from ``bert-real``) starts only once its source is built. After each bundle is written it calls
``on_built(name)``; ``gpnarx serve`` makes the app rescan its registry there
(``ServiceState.reload_from_thread``), so each model is served as soon as it is written.
``status()`` is what ``/health/ready`` shows under ``startup`` (``service.schemas.StartupStatus``).
A build that fails is logged and listed in ``failed`` (and so are the defaults derived from it); the
others go on.

``ChildBuild`` is the build function ``gpnarx serve`` uses: ``gpnarx build-defaults --only NAME``
in a child process, so the training has its own BLAS threads (the service limits its own to one
per worker; with several builds at once each child gets its share of the cores) and its own memory,
and its Python work never competes with the server's event loop for the GIL. Builds after the first
one run at a lower CPU priority (nice 10), so they do not slow the answers of the models already
served. The CLI package sits on top of both ``gpnarx.training`` and ``gpnarx.service``; this module
imports neither (stdlib only).
"""
from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

LATER_NICE = 10


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


#: most default builds run at once (memory: each is its own process holding its training data)
MAX_BUILD_JOBS = 4
#: BLAS / OpenMP thread variables a child build gets when several run at once
THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def available_cores() -> int:
    """CPU cores this process may run on (its affinity where the OS tells it, else the CPU count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def build_jobs(n_builds: int | None = None) -> int:
    """Default builds to run at once: the available cores, at most ``MAX_BUILD_JOBS`` and ``n_builds``."""
    jobs = min(available_cores(), MAX_BUILD_JOBS)
    return max(1, min(jobs, n_builds) if n_builds else jobs)


class DefaultBuilder:
    """Build ``pending`` names with ``build(name)`` in background threads, ``jobs`` at a time, in order.

    ``depends``: {name: the name it is derived from}; such a name starts after its source is built (or
    present), and fails without a build when its source failed. ``present``: defaults already in the
    registry (listed as built); ``skipped``: {name: reason}. ``on_built(name)``: called after each
    successful build, before the name is listed as built (the caller loads the bundle there; an
    exception marks the build failed). ``log``: one-line messages. ``build`` must allow concurrent
    calls when ``jobs`` > 1 (``ChildBuild`` does).
    """

    def __init__(self, pending, build, on_built=None, present=(), skipped=None, log=None, jobs: int = 1,
                 depends=None):
        if int(jobs) < 1:
            raise ValueError(f"jobs must be at least 1, got {jobs}")
        self.build = build
        self.on_built = on_built
        self.log = log or (lambda msg: None)
        self.jobs = int(jobs)
        self.depends = dict(depends or {})
        self._lock = threading.Condition()
        self._built = list(present)
        self._pending = list(pending)
        self._building: list[str] = []
        self._failed: dict[str, str] = {}
        self._skipped = dict(skipped or {})
        self.seconds: dict[str, float] = {}
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    def status(self) -> dict:
        """Built, building, pending, failed and skipped names (``service.schemas.StartupStatus``)."""
        with self._lock:
            return {"built": list(self._built), "building": list(self._building),
                    "pending": list(self._pending), "failed": list(self._failed), "skipped": list(self._skipped),
                    "reasons": {**self._skipped, **self._failed},
                    "done": not self._building and not self._pending}

    @property
    def n_built(self) -> int:
        with self._lock:
            return len(self._built)

    def start(self) -> "DefaultBuilder":
        if self._pending and not self._threads:
            n = min(self.jobs, len(self._pending))
            self._threads = [threading.Thread(target=self.run, name=f"gpnarx-default-builder-{k}", daemon=True)
                             for k in range(n)]
            for t in self._threads:
                t.start()
        return self

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the builds to end; True when they have."""
        deadline = None if timeout is None else time.monotonic() + timeout
        for t in self._threads:
            t.join(None if deadline is None else max(0.0, deadline - time.monotonic()))
        return not any(t.is_alive() for t in self._threads)

    def stop(self, timeout: float | None = 30.0) -> None:
        """Build nothing more; the running builds are stopped if the build function has a ``stop()``."""
        self._stop.set()
        with self._lock:
            self._lock.notify_all()
        stop = getattr(self.build, "stop", None)
        if callable(stop):
            stop()
        self.join(timeout)

    def _next(self) -> str | None:
        """The first pending name whose source is not still to come (under the lock); None: wait or end."""
        for name in list(self._pending):
            source = self.depends.get(name)
            if source in self._failed:
                self._pending.remove(name)
                self._failed[name] = f"derived from {source}, which failed"
                self.log(f"default bundle {name} not built: {self._failed[name]}")
                self._lock.notify_all()
                continue
            if source is not None and (source in self._pending or source in self._building):
                continue
            self._pending.remove(name)
            return name
        return None

    def run(self) -> None:
        while True:
            with self._lock:
                while True:
                    if self._stop.is_set() or not self._pending:
                        return
                    name = self._next()
                    if name is not None:
                        break
                    if not self._pending:
                        return
                    self._lock.wait(1.0)
                self._building.append(name)
            t0 = time.monotonic()
            try:
                self.build(name)
                if self._stop.is_set():
                    return
                if self.on_built is not None:
                    self.on_built(name)
            except Exception as exc:
                if self._stop.is_set():
                    return
                reason = _one_line(exc)
                with self._lock:
                    self._failed[name] = reason
                    self._building.remove(name)
                    self._lock.notify_all()
                self.log(f"default bundle {name} failed after {time.monotonic() - t0:.0f} s: {reason}; "
                         f"serving the others")
                continue
            dt = time.monotonic() - t0
            with self._lock:
                self.seconds[name] = dt
                self._built.append(name)
                self._building.remove(name)
                self._lock.notify_all()
            self.log(f"default bundle {name} built and loaded in {dt:.0f} s")


class ChildBuild:
    """``build(name)``: ``python -m gpnarx build-defaults --registry ROOT --only NAME --json`` in a child.

    The child's stderr lines are passed on to ``log``; a non-zero exit raises ``RuntimeError`` with
    the child's last stderr line. ``nice_after_first``: builds after the first one run at nice
    ``LATER_NICE``. ``threads``: BLAS / OpenMP threads of each child (``THREAD_VARS``, unless the
    environment already sets them); None leaves them to the libraries. Several calls may run at once
    (one child each).
    """

    def __init__(self, root, log=None, nice_after_first: bool = True, env=None, threads: int | None = None):
        self.root = str(root)
        self.log = log or (lambda line: print(line, file=sys.stderr, flush=True))
        self.nice_after_first = nice_after_first
        self.env = env
        self.threads = threads
        self.n_started = 0
        self._procs: list[subprocess.Popen] = []
        self._lock = threading.Lock()
        self._stopped = False

    @property
    def _proc(self) -> subprocess.Popen | None:
        """A running child (the first started), or None."""
        with self._lock:
            return self._procs[0] if self._procs else None

    def command(self, name: str) -> list[str]:
        return [sys.executable, "-m", "gpnarx", "build-defaults", "--registry", self.root, "--only", name, "--json"]

    def child_env(self) -> dict | None:
        """The child's environment: ``env`` (or this process's) with ``threads`` BLAS threads."""
        if self.threads is None:
            return self.env
        env = dict(os.environ if self.env is None else self.env)
        for var in THREAD_VARS:
            env.setdefault(var, str(int(self.threads)))
        return env

    def __call__(self, name: str) -> None:
        with self._lock:
            if self._stopped:
                raise RuntimeError("the server is stopping")
            # its own session: a Ctrl-C meant for the server does not kill the build half-way with a
            # spurious failure line; the server's shutdown stops it (stop())
            proc = subprocess.Popen(self.command(name), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                    stderr=subprocess.PIPE, text=True, errors="replace", env=self.child_env(),
                                    start_new_session=True)
            self._procs.append(proc)
            later = self.n_started > 0
            self.n_started += 1
        if later and self.nice_after_first and hasattr(os, "setpriority"):
            try:
                os.setpriority(os.PRIO_PROCESS, proc.pid, LATER_NICE)
            except OSError:  # pragma: no cover - the child already gone, or not allowed
                pass
        last = ""
        for line in proc.stderr:
            line = line.rstrip("\r\n")
            if line.strip():
                last = line.strip()
                self.log(line)
        rc = proc.wait()
        with self._lock:
            self._procs.remove(proc)
        if rc != 0:
            raise RuntimeError(last or f"the build of {name} exited with code {rc}")

    def stop(self, timeout: float = 10.0) -> None:
        """Terminate the running children (if any); later calls refuse to start."""
        with self._lock:
            self._stopped = True
            procs = list(self._procs)
        for proc in procs:
            if proc.poll() is None:
                proc.terminate()
        for proc in procs:
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:  # pragma: no cover
                proc.kill()
