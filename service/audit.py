"""The audit trail: one JSON line per novelty verdict (and per predict with ``GPNARX_AUDIT_PREDICTS``).

``GPNARX_AUDIT_LOG`` names the target: a file path (appended to), an fsspec URL (opened in append
mode through fsspec; a store that cannot append counts failed writes), ``-`` or unset for stdout,
``off`` for none. Each line holds::

    time            UTC, ISO 8601 with milliseconds
    request_id      the request's X-Request-ID (service.observability)
    client          the API key's id: the first 12 hex digits of its SHA-256 (never the key);
                    "anonymous" when the request sent no key
    operation       "novelty" or "predict"
    slot            the record's index in a batch; null for a single call
    model, version  the bundle that answered
    record_sha256   SHA-256 of the record: u then y (when sent) as little-endian float64 bytes
    n_samples       samples of u
    score, threshold, verdict   the novelty answer (null for a predict)
    out_of_range, diverged_paths

Writing never blocks or fails an answer: ``record`` only puts the line on a bounded queue
(``GPNARX_AUDIT_QUEUE``; a full queue drops the line and counts it) and one background thread
writes. A call on the event loop also leaves the record's hash to a thread of the trail (at most
``MAX_HASHING`` records waiting). A write that fails (unwritable path, full disk, unreachable store) counts its lines as
failed, keeps the error for ``/health/ready`` (``audit``; readiness is not failed) and reopens the
target on the next line. ``/metrics``: ``gpnarx_audit_lines_total{outcome}`` (written, failed,
dropped), ``gpnarx_audit_lines_lost_total`` (failed + dropped), ``gpnarx_audit_write_failures_total`` and
``gpnarx_audit_reopens_total{reason}``.

A local file (a path or ``file://``) is written through an ``O_APPEND`` descriptor, one ``os.write`` per line:

- before each batch of lines the path's device and inode are compared with the open file's: a file deleted
  or renamed (logrotate without ``copytruncate``) is reopened (created again at the path), so no line goes
  to a deleted inode and lines after a rotation go to the new file; ``reopen()`` (SIGHUP under
  ``gpnarx serve``) does the same at once. A file truncated in place (``copytruncate``) needs nothing: the
  next append starts at its new end;
- a line is never left torn: a write that fails or comes back short is cut off again (``ftruncate`` to the
  file's length before it) and the line counted as failed; where that is impossible the fragment is ended
  with a newline before the next line (``torn`` counts those), so the fragment stands alone and every other
  line parses. A file that already ends in a fragment (a process killed mid-line) gets a newline first too.
"""
from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import queue
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime, timezone

import numpy as np

log = logging.getLogger("gpnarx.service.audit")

OFF = "off"
STDOUT = "-"
#: lines written per batch of the writer thread (then flushed)
_CHUNK = 256
#: records at most waiting to be hashed off the event loop (``AuditTrail.record(offload=True)``)
MAX_HASHING = 64
#: why the writer reopened a local file (``gpnarx_audit_reopens_total{reason}``)
REOPEN_REASONS = ("deleted", "rotated", "signal", "error")


def client_id(api_key: str | None) -> str:
    """The id of the API key a request sent: its SHA-256's first 12 hex digits, or 'anonymous'."""
    if not api_key:
        return "anonymous"
    return hashlib.sha256(api_key.encode("utf-8", "replace")).hexdigest()[:12]


def record_sha256(u, y=None) -> str:
    """SHA-256 of u then y (when given) as little-endian float64 bytes."""
    h = hashlib.sha256(np.ascontiguousarray(np.asarray(u, dtype="<f8")).tobytes())
    if y is not None:
        h.update(np.ascontiguousarray(np.asarray(y, dtype="<f8")).tobytes())
    return h.hexdigest()


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _number(v):
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return v if np.isfinite(v) else None


def _request_id_of(line: str) -> str | None:
    try:
        return json.loads(line).get("request_id")
    except (ValueError, AttributeError):
        return None


def shown_target(target: str | None) -> str:
    """The target as /health/ready shows it: no user or password of a URL."""
    if not target or target == STDOUT:
        return "stdout"
    if "://" in target and "@" in target.split("://", 1)[1].split("/", 1)[0]:
        scheme, rest = target.split("://", 1)
        host_path = rest.split("@", 1)[1]
        return f"{scheme}://{host_path}"
    return target


class AuditTrail:
    """A bounded queue of audit lines and the thread that appends them to the target."""

    def __init__(self, target: str | None = None, queue_size: int = 10000, predicts: bool = False):
        target = (target or "").strip() or STDOUT
        self.enabled = target.lower() != OFF
        self.target = target
        self.predicts = bool(predicts)
        self.queue: queue.Queue = queue.Queue(maxsize=max(1, int(queue_size)))
        self.written = 0
        self.failed = 0  # lines whose write failed
        self.failures = 0  # failed write attempts
        self.dropped = 0  # lines refused by a full queue
        self.torn = 0  # fragments of failed writes that could not be cut off (ended by a newline instead)
        self.reopens = dict.fromkeys(REOPEN_REASONS, 0)  # local file reopened, by reason
        self.last_error: str | None = None
        self.last_error_time: str | None = None
        self._last_ok = True  # whether the last write attempt succeeded
        self._lock = threading.Lock()
        self._hashing = 0  # records waiting for or being hashed on the hash thread (record(offload=True))
        self._hash_pool: ThreadPoolExecutor | None = None
        self._thread: threading.Thread | None = None
        self._fh = None
        self._fd: int | None = None  # a local file's O_APPEND descriptor (``_write_local``)
        self._fd_id: tuple | None = None  # (st_dev, st_ino) of the file it holds
        self._need_newline = False  # the file ends in a fragment: the next line starts on a new line
        self._reopen_asked = False  # reopen() called (SIGHUP): the writer reopens before its next line
        self._reopen_next: str | None = None  # why the next open is a reopen (counted once it is done)
        self._closed = False

    @classmethod
    def from_settings(cls, settings) -> AuditTrail:
        return cls(settings.audit_log, settings.audit_queue, settings.audit_predicts)

    # ------------------------------------------------------------------ the request side
    def wants(self, operation: str) -> bool:
        return self.enabled and (operation == "novelty" or (operation == "predict" and self.predicts))

    def record(self, operation: str, out: dict, req, request_id: str | None, client: str,
               slot: int | None = None, offload: bool = False) -> None:
        """Queue the audit line of one answer (never raises; a full queue drops the line and counts it).

        ``offload``: hash the record on the trail's own thread rather than the caller's (the event loop
        calls with it: hashing a 65536-sample record's lists takes milliseconds); at most
        ``MAX_HASHING`` records wait for it, a further one is dropped and counted."""
        if not self.wants(operation):
            return
        if offload:
            with self._lock:
                busy = self._hashing >= MAX_HASHING or self._closed
                if not busy:
                    self._hashing += 1
                else:
                    self.dropped += 1
            if busy:
                return
            try:
                self._hasher().submit(self._record_offloaded, _now(), operation, out, req, request_id, client, slot)
            except Exception:  # pragma: no cover - interpreter shutdown
                with self._lock:
                    self._hashing -= 1
                    self.dropped += 1
            return
        self._record(_now(), operation, out, req, request_id, client, slot)

    def _hasher(self) -> ThreadPoolExecutor:
        if self._hash_pool is None:
            with self._lock:
                if self._hash_pool is None:
                    self._hash_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="gpnarx-audit-hash")
        return self._hash_pool

    def _record_offloaded(self, *args) -> None:
        try:
            self._record(*args)
        finally:
            with self._lock:
                self._hashing -= 1

    def _record(self, now: str, operation: str, out: dict, req, request_id: str | None, client: str,
                slot: int | None) -> None:
        try:
            y = getattr(req, "y", None)
            line = {"time": now, "request_id": request_id, "client": client, "operation": operation,
                    "slot": slot, "model": out.get("model"), "version": out.get("version"),
                    "record_sha256": record_sha256(req.u, y), "n_samples": len(req.u),
                    "score": _number(out.get("score")), "threshold": _number(out.get("threshold")),
                    "verdict": out.get("verdict"), "out_of_range": list(out.get("out_of_range") or []),
                    "diverged_paths": int(out.get("diverged_paths") or 0)}
            self._put(json.dumps(line, ensure_ascii=False, separators=(",", ":")))
        except Exception:  # an answer is never lost to its audit line
            log.exception("audit line not queued")
            with self._lock:
                self.dropped += 1

    def _put(self, text: str) -> None:
        self._start()
        try:
            self.queue.put_nowait(text)
        except queue.Full:
            with self._lock:
                self.dropped += 1
            if self.dropped == 1 or self.dropped % 1000 == 0:
                log.warning("audit queue full (GPNARX_AUDIT_QUEUE=%d): %d line(s) dropped so far",
                            self.queue.maxsize, self.dropped)

    def _start(self) -> None:
        if self._thread is not None or self._closed:
            return
        with self._lock:
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="gpnarx-audit", daemon=True)
                self._thread.start()

    # ------------------------------------------------------------------ the writer thread
    def reopen(self) -> None:
        """Close and open the target again before the next line (SIGHUP under ``gpnarx serve``, after a
        rotation); safe from any thread or a signal handler: the writer thread does it."""
        self._reopen_asked = True

    def _local_path(self) -> str | None:
        """The target's path when it is a local file (a path or ``file://`` URL), else None."""
        if self.target == STDOUT or ("://" in self.target and not self.target.startswith("file://")):
            return None
        return self.target.removeprefix("file://")

    def _open_fd(self, path: str) -> None:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o666)
        st = os.fstat(fd)
        tail = b"\n"
        if st.st_size > 0:
            try:
                with open(path, "rb") as fh:
                    fh.seek(-1, os.SEEK_END)
                    tail = fh.read(1) or b"\n"
            except OSError:  # a write-only file: taken as whole
                pass
        self._fd, self._fd_id = fd, (st.st_dev, st.st_ino)
        self._need_newline = tail != b"\n"  # a fragment left by a killed process: not glued to our line
        if self._reopen_next is not None:
            with self._lock:
                self.reopens[self._reopen_next] += 1
            self._reopen_next = None

    def _close_fd(self) -> None:
        fd, self._fd, self._fd_id = self._fd, None, None
        if fd is not None:
            try:
                os.close(fd)
            except OSError:  # pragma: no cover
                pass

    def _check_file(self, path: str) -> None:
        """Reopen when asked to, or when the path no longer names the open file (deleted or renamed)."""
        if self._fd is not None and self._reopen_asked:
            self._reopen_asked = False
            self._close_fd()
            self._reopen_next = "signal"
        elif self._fd is not None:
            try:
                st = os.stat(path)
                why = None if (st.st_dev, st.st_ino) == self._fd_id else "rotated"
            except FileNotFoundError:
                why = "deleted"
            if why is not None:
                self._close_fd()
                self._reopen_next = why
        self._reopen_asked = False
        if self._fd is None:
            self._open_fd(path)

    def _write_line(self, data: bytes) -> None:
        """Append one line with one ``os.write``; on a failed or short write, cut the file back to its length
        before it (or end the fragment with a newline) and raise."""
        fd = self._fd
        if self._need_newline:
            data = b"\n" + data
        before = os.fstat(fd).st_size
        try:
            n = os.write(fd, data)
            if n == len(data):
                self._need_newline = False
                return
            error: OSError = OSError(errno.EIO, f"short write: {n} of {len(data)} bytes")
        except OSError as exc:
            error = exc
        try:
            if os.fstat(fd).st_size > before:
                os.ftruncate(fd, before)  # the fragment goes; O_APPEND writes on at the new end
        except OSError:
            self._need_newline = True  # the fragment stays: the next line starts on a line of its own
            with self._lock:
                self.torn += 1
        raise error

    def _write_local(self, path: str, lines: list[str]) -> int:
        """Write ``lines`` to the local file; the number written before a failure (which raises, its
        ``written`` attribute set)."""
        self._check_file(path)
        done = 0
        try:
            for line in lines:
                self._write_line((line + "\n").encode("utf-8"))
                done += 1
        except OSError as exc:
            exc.written = done
            raise
        return done

    def _open(self):
        if "://" in self.target and not self.target.startswith("file://"):
            import fsspec

            return fsspec.open(self.target, "a", encoding="utf-8").open()
        path = self.target.removeprefix("file://")
        return open(path, "a", encoding="utf-8")  # noqa: SIM115 - kept open by the writer thread

    def _close_fh(self) -> None:
        fh, self._fh = self._fh, None
        if fh is not None and fh is not sys.stdout:
            try:
                fh.close()
            except Exception:  # pragma: no cover - a broken target
                pass

    def _write(self, lines: list[str]) -> None:
        path = self._local_path()
        try:
            if path is not None:
                self._write_local(path, lines)
            else:
                if self.target == STDOUT:  # looked up on each write: sys.stdout may be replaced (capture, redirect)
                    fh = sys.stdout
                else:
                    if self._fh is None:
                        self._fh = self._open()
                    fh = self._fh
                fh.write("".join(line + "\n" for line in lines))
                fh.flush()
        except Exception as exc:
            done = getattr(exc, "written", 0)
            if path is not None and self._fd is not None:
                self._close_fd()  # reopened on the next line
                self._reopen_next = "error"
            else:
                self._close_fh()  # reopened on the next line
            lost = lines[done:]
            with self._lock:
                self.written += done
                self.failed += len(lost)
                self.failures += 1
                self.last_error = f"{type(exc).__name__}: {exc}"[:500]
                self.last_error_time = _now()
                self._last_ok = False
            if self.failures == 1 or self.failures % 100 == 0:  # named by the first lost line's request id
                log.error("audit trail %s: write failed (%d line(s) lost so far): %s", shown_target(self.target),
                          self.failed, self.last_error, extra={"request_id": _request_id_of(lost[0])})
            return
        with self._lock:
            self.written += len(lines)
            self._last_ok = True

    def _run(self) -> None:
        while True:
            first = self.queue.get()
            if first is None:
                return
            lines, stop = [first], False
            while len(lines) < _CHUNK:
                try:
                    nxt = self.queue.get_nowait()
                except queue.Empty:
                    break
                if nxt is None:
                    stop = True
                    break
                lines.append(nxt)
            self._write(lines)
            for _ in range(len(lines) + stop):
                self.queue.task_done()
            if stop:
                self._close_fh()
                self._close_fd()
                return

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until the queued lines are written or failed (tests, shutdown); False on timeout."""
        deadline = time.monotonic() + timeout
        while (self._hashing or self.queue.unfinished_tasks) and time.monotonic() < deadline:
            time.sleep(0.005)
        return not (self._hashing or self.queue.unfinished_tasks)

    def close(self, timeout: float = 5.0) -> None:
        """Write what is queued (up to ``timeout`` s) and stop the threads."""
        self.flush(timeout)
        self._closed = True
        if self._hash_pool is not None:
            self._hash_pool.shutdown(wait=False)
        if self._thread is None:
            return
        try:
            self.queue.put(None, timeout=max(0.1, timeout))
        except queue.Full:  # pragma: no cover - the writer is stuck
            return
        self._thread.join(timeout)

    def status(self) -> dict:
        """What /health/ready shows under ``audit``."""
        with self._lock:
            return {"target": shown_target(self.target) if self.enabled else OFF,
                    "ok": self._last_ok,
                    "written": self.written, "failed": self.failed, "dropped": self.dropped,
                    "lost": self.failed + self.dropped, "torn": self.torn,
                    "reopened": sum(self.reopens.values()), "reopens": dict(self.reopens),
                    "queued": self.queue.qsize(), "last_error": self.last_error,
                    "last_error_time": self.last_error_time}
