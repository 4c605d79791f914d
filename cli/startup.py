"""First start of ``gpnarx serve`` on the default registry: build the missing defaults in the background.

The server opens its port at once (``/health/live`` answers while bundles are built) and
``DefaultBuilder`` builds the missing default bundles one at a time, in the order
``training.defaults`` gives (lightest first). After each bundle is written it calls
``on_built(name)``; ``gpnarx serve`` makes the app rescan its registry there
(``ServiceState.reload_from_thread``), so each model is served as soon as it is written.
``status()`` is what ``/health/ready`` shows under ``startup`` (``service.schemas.StartupStatus``).
A build that fails is logged and listed in ``failed``; the others go on.

``ChildBuild`` is the build function ``gpnarx serve`` uses: ``gpnarx build-defaults --only NAME``
in a child process, so the training has its own BLAS threads (the service limits its own to one
per worker) and its own memory, and its Python work never competes with the server's event loop
for the GIL. Builds after the first loaded model run at a lower CPU priority (nice 10), so they
do not slow the answers of the models already served. The CLI package sits on top of both
``gpnarx.training`` and ``gpnarx.service``; this module imports neither (stdlib only).
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


class DefaultBuilder:
    """Build ``pending`` names one at a time with ``build(name)`` in a background thread.

    ``present``: defaults already in the registry (listed as built); ``skipped``: {name: reason}.
    ``on_built(name)``: called after each successful build, before the name is listed as built (the
    caller loads the bundle there; an exception marks the build failed). ``log``: one-line messages.
    """

    def __init__(self, pending, build, on_built=None, present=(), skipped=None, log=None):
        self.build = build
        self.on_built = on_built
        self.log = log or (lambda msg: None)
        self._lock = threading.Lock()
        self._built = list(present)
        self._pending = list(pending)
        self._building: str | None = None
        self._failed: dict[str, str] = {}
        self._skipped = dict(skipped or {})
        self.seconds: dict[str, float] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def status(self) -> dict:
        """Built, building, pending, failed and skipped names (``service.schemas.StartupStatus``)."""
        with self._lock:
            return {"built": list(self._built), "building": [self._building] if self._building else [],
                    "pending": list(self._pending), "failed": list(self._failed), "skipped": list(self._skipped),
                    "reasons": {**self._skipped, **self._failed},
                    "done": self._building is None and not self._pending}

    @property
    def n_built(self) -> int:
        with self._lock:
            return len(self._built)

    def start(self) -> "DefaultBuilder":
        if self._pending and self._thread is None:
            self._thread = threading.Thread(target=self.run, name="gpnarx-default-builder", daemon=True)
            self._thread.start()
        return self

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the builds to end; True when they have."""
        if self._thread is not None:
            self._thread.join(timeout)
            return not self._thread.is_alive()
        return True

    def stop(self, timeout: float | None = 30.0) -> None:
        """Build nothing more; the running build is stopped if its build function has a ``stop()``."""
        self._stop.set()
        stop = getattr(self.build, "stop", None)
        if callable(stop):
            stop()
        self.join(timeout)

    def run(self) -> None:
        while True:
            with self._lock:
                if self._stop.is_set() or not self._pending:
                    self._building = None
                    return
                name = self._pending.pop(0)
                self._building = name
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
                    self._building = None
                self.log(f"default bundle {name} failed after {time.monotonic() - t0:.0f} s: {reason}; "
                         f"serving the others")
                continue
            dt = time.monotonic() - t0
            with self._lock:
                self.seconds[name] = dt
                self._built.append(name)
                self._building = None
            self.log(f"default bundle {name} built and loaded in {dt:.0f} s")


class ChildBuild:
    """``build(name)``: ``python -m gpnarx build-defaults --registry ROOT --only NAME --json`` in a child.

    The child's stderr lines are passed on to ``log``; a non-zero exit raises ``RuntimeError`` with
    the child's last stderr line. ``nice_after_first``: builds after the first one run at nice
    ``LATER_NICE``.
    """

    def __init__(self, root, log=None, nice_after_first: bool = True, env=None):
        self.root = str(root)
        self.log = log or (lambda line: print(line, file=sys.stderr, flush=True))
        self.nice_after_first = nice_after_first
        self.env = env
        self.n_started = 0
        self._proc: subprocess.Popen | None = None
        self._lock = threading.Lock()
        self._stopped = False

    def command(self, name: str) -> list[str]:
        return [sys.executable, "-m", "gpnarx", "build-defaults", "--registry", self.root, "--only", name, "--json"]

    def __call__(self, name: str) -> None:
        with self._lock:
            if self._stopped:
                raise RuntimeError("the server is stopping")
            # its own session: a Ctrl-C meant for the server does not kill the build half-way with a
            # spurious failure line; the server's shutdown stops it (stop())
            proc = subprocess.Popen(self.command(name), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                    stderr=subprocess.PIPE, text=True, errors="replace", env=self.env,
                                    start_new_session=True)
            self._proc = proc
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
            self._proc = None
        if rc != 0:
            raise RuntimeError(last or f"the build of {name} exited with code {rc}")

    def stop(self, timeout: float = 10.0) -> None:
        """Terminate the running child (if any); later calls refuse to start."""
        with self._lock:
            self._stopped = True
            proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:  # pragma: no cover
                proc.kill()
