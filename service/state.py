"""The state of one service app: the registry (swapped atomically on reload), the executor,
metrics and settings; routes reach it with ``Depends(get_state)`` (``service.deps``)."""
from __future__ import annotations

import asyncio
import logging
import math
from pathlib import Path

from fastapi import Request

from gpnarx.storage.bundle import BundleError, check_name
from gpnarx.storage.registry import Registry, check_version_ref
from gpnarx.storage.remote import StorageError

from .metrics import ServiceMetrics
from .problems import ProblemError
from .settings import Settings
from .worker import Abandoned, BoundedExecutor, CancelToken, JobSize, Overloaded, QueueTimeout, TimedOut, WontStart

log = logging.getLogger("gpnarx.service")


class ServiceState:
    """Registry (swapped atomically on reload), executor, metrics and settings of one app.

    The registry is lazy: every version is verified when first seen, its model built on first use
    (at most ``settings.max_loaded`` kept). ``reload`` (admin route, SIGHUP) and the poll
    (``settings.registry_poll``) swap in a rescan; a registry that cannot be read keeps the last
    good one serving (``registry_error`` says why).
    """

    def __init__(self, registry_dir, settings: Settings, startup_status=None):
        self.settings = settings
        # start-up hook: a callable returning a dict (schemas.StartupStatus) of the bundles a launcher is
        # still building into the registry (``gpnarx serve`` without --registry); shown by /health/ready
        self.startup_status = startup_status
        self.loop: asyncio.AbstractEventLoop | None = None  # the server's loop while the app runs
        self.registry_dir = registry_dir if registry_dir else None  # a folder or an fsspec URL
        self.registry = Registry(self.registry_dir or Path("/nonexistent-gpnarx-registry"), lazy=True,
                                 max_loaded=settings.max_loaded)
        self.registry_error: str | None = None
        if self.registry_dir is not None:
            try:
                self.registry.scan()
            except StorageError as exc:  # unreachable store: not ready; the poll and reload try again
                self.registry_error = str(exc)
                log.error("the registry could not be read: %s", exc)
        self.leftovers_removed = self._clean_leftovers(self.registry)
        self.executor = BoundedExecutor(settings.workers, settings.queue_size)
        self.metrics = ServiceMetrics(self)
        self.reload_lock = asyncio.Lock()
        self.reloads = 0
        self.polls = 0
        self.held: dict | None = None  # a suspect scan held back (``_hold``); shown by /health/ready
        self._pending: tuple | None = None  # (listing, consecutive scans that showed it) of a held scan
        self._reported = self._listed(self.registry)  # what the last reload answered against

    def _clean_leftovers(self, registry: Registry) -> int:
        """Remove what killed writes left in ``registry`` after its scan (``Registry.remove_leftovers``:
        local ``NAME/.tmp-*`` folders whose writer is gone from this host at once; unpublished versions
        on an object store, and folders of another host, once ``settings.registry_leftover_age`` old);
        logged at WARNING. A registry this server may not write to is left as it is (logged)."""
        if self.registry_dir is None:
            return 0
        try:
            removed = registry.remove_leftovers(self.settings.leftover_seconds)
        except (OSError, StorageError) as exc:  # a read-only registry or store: nothing of ours to clean
            log.info("registry: leftovers of killed writes not removed (%s)", exc)
            return 0
        for path in removed:
            log.warning("registry: removed %s, what a killed write left", path)
        return len(removed)

    def refused(self, registry: Registry | None = None) -> list[dict]:
        reg = registry or self.registry
        root = str(reg.root).rstrip("/") + "/"
        out = []
        for r in reg.refused:
            path = r["path"][len(root):] if r["path"].startswith(root) else Path(r["path"]).name
            out.append({"path": path, "reason": r["reason"].replace(root, "")})
        return out

    def models(self, registry: Registry | None = None) -> dict:
        reg = registry or self.registry
        return {name: reg.versions(name) for name in reg.names()}

    def n_bundles(self, registry: Registry | None = None) -> int:
        reg = registry or self.registry
        return sum(len(v) for v in reg.bundles.values())

    @staticmethod
    def _listed(reg: Registry) -> set:
        return {f"{n}:{v}" for n, vs in reg.bundles.items() for v in vs}

    async def reload(self, poll: bool = False, accept_removal: bool = False) -> dict:
        """Rescan the registry and swap it in. ``added``/``removed`` compare with the previous reload
        (or the start), so versions a poll picked up meanwhile are still reported; a poll does not
        move that reference.

        A scan that drops every listed version, or more than ``settings.registry_drop_share`` of
        them, is held (``_hold``): the last good registry keeps serving until the same listing is
        seen on ``settings.confirm_scans`` consecutive scans, or ``accept_removal``."""
        if self.registry_dir is None:
            raise ProblemError(409, "no registry folder is configured; nothing to reload")
        trigger = "poll" if poll else "reload"
        async with self.reload_lock:
            old = self.registry
            try:
                new = await asyncio.to_thread(old.rescan)
                self.metrics.leftovers.inc(await asyncio.to_thread(self._clean_leftovers, new))
            except StorageError as exc:
                self.registry_error = str(exc)
                self.metrics.scans.labels(trigger, "error").inc()
                raise ProblemError(503, f"the registry could not be read ({exc}); the versions listed before "
                                        f"keep serving", headers={"Retry-After": str(self.settings.retry_after)}
                                   ) from None
            self.registry_error = None
            held = self._hold(old, new, accept_removal)
            if held is not None:
                self.metrics.scans.labels(trigger, "held").inc()
                return {"bundles": self.n_bundles(old), "models": self.models(old), "refused": self.refused(old),
                        "added": [], "removed": [], "held": held}
            self.registry = new  # atomic swap: in-flight requests keep the bundle they hold
            if poll:
                self.polls += 1
            else:
                self.reloads += 1
            before, after = (self._listed(old), self._listed(new)) if poll else (self._reported, self._listed(new))
            if not poll:
                self._reported = after
            changed = self._listed(old) != self._listed(new) or len(old.refused) != len(new.refused)
            self.metrics.scans.labels(trigger, "changed" if changed else "unchanged").inc()
            self.metrics.versions_added.inc(len(self._listed(new) - self._listed(old)))
            self.metrics.versions_removed.inc(len(self._listed(old) - self._listed(new)))
        self.metrics.update_bundles()
        if not poll or changed:
            (log.warning if before - after else log.info)(
                "registry %s: %d bundles, %d refused; added %s, removed %s", "polled" if poll else "reloaded",
                self.n_bundles(new), len(new.refused), sorted(after - before) or "none",
                sorted(before - after) or "none")
        return {"bundles": self.n_bundles(new), "models": self.models(new), "refused": self.refused(new),
                "added": sorted(after - before), "removed": sorted(before - after)}

    def _hold(self, old: Registry, new: Registry, accept: bool) -> dict | None:
        """None when ``new`` may replace ``old``; else what is held (``schemas.RegistryHeld``), logged.

        A scan is suspect when it drops every version ``old`` listed, or more than
        ``registry_drop_share`` of them (an emptied or wiped store, a wrong bucket or prefix, a
        volume not mounted). A suspect listing is served once the same listing has been seen on
        ``settings.confirm_scans`` consecutive scans, or at once with ``accept`` (the admin action).
        """
        before, after = old.listed(), new.listed()
        dropped = before - after
        share = self.settings.registry_drop_share
        suspect = bool(before) and bool(dropped) and (dropped == before or len(dropped) > share * len(before))
        if not suspect:
            self.held = self._pending = None
            return None
        key = frozenset(after)
        seen = self._pending[1] + 1 if self._pending is not None and self._pending[0] == key else 1
        needed = self.settings.confirm_scans
        if accept or seen >= needed:
            how = "by an admin reload with accept_removal" if accept else f"after {seen} consecutive scans"
            log.warning("registry: a listing without %d of %d versions (%s) is served now, %s", len(dropped),
                        len(before), ", ".join(sorted(dropped)[:10]), how)
            self.held = self._pending = None
            self.metrics.scans_accepted.inc()
            return None
        self._pending = (key, seen)
        detail = (f"the last registry scan lists {len(after)} version(s) and drops {len(dropped)} of the "
                  f"{len(before)} served ({'all' if dropped == before else f'more than {share:g} of them'}); "
                  f"the last good registry keeps serving until the same listing is seen on {needed} consecutive "
                  f"scans ({seen} so far) or POST /v1/admin/reload?accept_removal=true")
        self.held = {"detail": detail, "served": len(before), "listed": len(after), "dropped": sorted(dropped)[:50],
                     "scans": seen, "needed": needed}
        log.warning("registry: %s", detail)
        return self.held

    def reload_from_thread(self, timeout: float | None = 300.0) -> dict:
        """``reload()`` called from another thread (e.g. a launcher that has just written a bundle).

        Runs on the server's event loop while the app runs (so it takes turns with admin reloads), else
        in this thread; returns reload()'s answer.
        """
        loop = self.loop
        if loop is not None and loop.is_running():
            return asyncio.run_coroutine_threadsafe(self.reload(), loop).result(timeout)
        return asyncio.run(self.reload())

    def startup(self) -> dict | None:
        """The start-up hook's status (None without a hook, or if the hook fails: logged)."""
        if self.startup_status is None:
            return None
        try:
            return self.startup_status()
        except Exception:  # pragma: no cover - a launcher's bug must not break readiness
            log.exception("the start-up status hook failed")
            return None

    def lookup(self, name: str, version: str | None, build: bool = True):
        """The bundle a name and a version or alias (None: latest) name: built (``build``) or the
        registry's verified entry (manifest and path; no model built). ProblemError otherwise."""
        try:
            check_name(name)
        except BundleError as exc:
            raise ProblemError(422, str(exc), "name") from None
        if version is not None:
            try:
                check_version_ref(version)
            except BundleError as exc:
                raise ProblemError(422, str(exc), "version") from None
        try:
            return self.registry.get(name, version) if build else self.registry.entry(name, version)
        except KeyError as exc:
            startup = self.startup() or {}
            if name not in self.registry.bundles and name in [*startup.get("building", []),
                                                               *startup.get("pending", [])]:
                raise ProblemError(503, f"model {name!r} is still being built at start-up (see /health/ready); "
                                        f"retry after {self.settings.retry_after} s", "name",
                                   headers={"Retry-After": str(self.settings.retry_after)}) from None
            msg = str(exc.args[0] if exc.args else "not found")
            msg = msg.replace(str(self.registry.root).rstrip("/") + "/", "")  # paths inside the registry only
            raise ProblemError(404, msg, "version" if name in self.registry.bundles else "name") from None

    async def alookup(self, name: str, version: str | None):
        """``lookup`` that builds a model not yet in memory on a thread (the event loop keeps serving)."""
        if self.registry.is_built(name, version):
            return self.lookup(name, version)
        return await asyncio.to_thread(self.lookup, name, version)

    def retry_after(self, after: float | None = None) -> int:
        """``Retry-After`` [s] of a busy answer: ``after``, or else the predicted time until a request would be
        admitted (a slot free, and the wait for a worker within the time limit: ``BoundedExecutor.
        retry_after``), at least ``settings.retry_after``, at most an hour."""
        if after is None:
            after = self.executor.retry_after(0.0, self.settings.request_timeout or None)
        return int(min(max(self.settings.retry_after, math.ceil(after)), 3600))

    def busy(self) -> ProblemError | None:
        """The 503 a compute request gets before its body is read (its size unknown yet), when the queue is
        full or the wait for a worker alone passes the time limit (``service.middleware``); else None. A
        request whose own predicted time would not fit is refused once its size is known (``run``)."""
        ex, timeout = self.executor, self.settings.request_timeout
        if ex.pending >= ex.capacity:
            why = f"all {ex.workers} workers are busy and {ex.queue_size} jobs are waiting"
        else:
            wait = ex.wait_estimate()
            if not (timeout and wait > timeout):
                return None
            why = f"the work queued ahead needs about {wait:.0f} s, more than the time limit of {timeout:g} s"
        self.metrics.shed.inc()
        after = self.retry_after()
        return ProblemError(503, f"the service is busy ({why}); retry after {after} s",
                            headers={"Retry-After": str(after)})

    async def run(self, fn, *args, request: Request | None = None, token: CancelToken | None = None,
                  work: JobSize | float = 1.0, too_slow: tuple[str, str] | None = None):
        """Run ``fn(*args)`` on the worker pool under the request deadline; cancel it if the client goes.

        ``token`` (the caller passes it to ``fn`` too) is set when a running job must stop; ``work``
        (a ``JobSize``: ``ops.job_size``) prices the job for admission; ``too_slow``: (advice, field) of
        the 504 when the job outlives the deadline, what this request can change to finish in time
        (``too_slow_advice``; default: a Monte Carlo record's).
        """
        too_slow = too_slow or too_slow_advice(True)
        timeout = self.settings.request_timeout or None
        watch = (lambda: _client_gone(request)) if request is not None else None
        try:
            return await self.executor.run(fn, *args, timeout=timeout, watch=watch, token=token, work=work)
        except QueueTimeout:
            self.metrics.timed_out.labels("queued").inc()
            after = self.retry_after()
            raise ProblemError(503, f"the service is busy: the request waited its whole time limit of {timeout:g} s "
                                    f"(GPNARX_REQUEST_TIMEOUT) for a worker; retry after {after} s",
                               headers={"Retry-After": str(after)}, limit=timeout) from None
        except WontStart as exc:
            if exc.need is not None and timeout is not None and exc.need > timeout:
                # too slow even on an idle service: a retry cannot help, what the request can change does
                self.metrics.timed_out.labels("predicted").inc()
                raise ProblemError(504, f"the request would not finish within its time limit of {timeout:g} s "
                                        f"(GPNARX_REQUEST_TIMEOUT): it needs about {exc.need:.2g} s on its own, by "
                                        f"the requests of its size run so far; {too_slow[0]}", too_slow[1],
                                   limit=timeout) from None
            self.metrics.shed.inc()
            after = self.retry_after(exc.retry_after)
            raise ProblemError(503, f"the service is busy ({exc}); retry after {after} s",
                               headers={"Retry-After": str(after)}, limit=timeout) from None
        except Overloaded as exc:
            self.metrics.shed.inc()
            after = self.retry_after()
            raise ProblemError(503, f"the service is busy ({exc}); retry after {after} s",
                               headers={"Retry-After": str(after)}) from None
        except TimedOut:
            self.metrics.timed_out.labels("running").inc()
            raise ProblemError(504, f"the request did not finish within its time limit of {timeout:g} s "
                                    f"(GPNARX_REQUEST_TIMEOUT); {too_slow[0]}", too_slow[1], limit=timeout) from None
        except Abandoned as exc:
            self.metrics.abandoned.inc()
            raise ProblemError(499, f"{exc}; the job was cancelled") from None


def too_slow_advice(monte_carlo: bool, batch: bool = False) -> tuple[str, str]:
    """(advice, field) of the 504 of a request whose job outlived its deadline: what it can change to finish in
    time, and the field to name (``monte_carlo``: it runs Monte Carlo paths; ``batch``: it is a batch)."""
    if batch:
        if monte_carlo:
            return "send fewer records per batch, shorter records, fewer mc_paths or method 'linear'", "mc_paths"
        return "send fewer records per batch, shorter records (a long record as a stream in chunks: docs/api.md)", \
            "requests"
    if monte_carlo:
        return "send fewer mc_paths, a shorter record or method 'linear'", "mc_paths"
    return "send a shorter record (a stream in chunks: docs/api.md, Streams)", "u"


async def _client_gone(request: Request) -> None:
    """Completes when the client disconnects (the body has already been read)."""
    while True:
        message = await request.receive()
        if message["type"] == "http.disconnect":
            return

