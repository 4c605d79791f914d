"""Reading the audit trail back: a model's recent novelty verdicts and scores, for a trend.

``service.audit`` writes the trail (one JSON line per novelty verdict); this module only reads it, from
the end of the file backwards, and never holds the writer up or changes the file. It is tolerant of what
a live, append-only log can hold: a line cut short by a write in progress or a crash, a line that is not
JSON or not an object, a line of another model or operation, a field of the wrong type. Such lines are
skipped (and counted), never an error. It is bounded: at most ``limit`` points and ``MAX_READ_BYTES`` bytes
of the file's end, read in ``BLOCK_BYTES`` blocks; a trail longer than that is read only in part
(``older_unread``).

Only a local file can be read back (``GPNARX_AUDIT_LOG`` a path or ``file://`` URL): a trail on stdout,
turned off or in an object store has no history here, and the answer says why (``available`` false and
``reason``).
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from datetime import datetime

from gpnarx.checks import is_int

from .audit import OFF, STDOUT, shown_target

#: the most of the file's end read for one history (older lines beyond it are not read)
MAX_READ_BYTES = 8 * 1024 * 1024
#: the file is read backwards in blocks of this size
BLOCK_BYTES = 64 * 1024
#: longest line taken as an audit line; a longer "line" (a damaged file) is skipped
MAX_LINE_BYTES = 64 * 1024
VERDICTS = ("healthy", "novel", "unjudged")


@dataclass
class History:
    """A model's novelty points from the trail, oldest first, and how the trail was read."""

    target: str
    available: bool
    reason: str | None = None
    points: list[dict] = field(default_factory=list)
    read_bytes: int = 0
    skipped_lines: int = 0
    older_unread: bool = False

    def as_dict(self) -> dict:
        return {"target": self.target, "available": self.available, "reason": self.reason, "points": self.points,
                "read_bytes": self.read_bytes, "skipped_lines": self.skipped_lines, "older_unread": self.older_unread}


def local_path(target: str | None) -> tuple[str | None, str | None]:
    """(path, None) when the trail ``target`` (GPNARX_AUDIT_LOG) is a local file, else (None, why not)."""
    target = (target or "").strip()
    if not target or target == STDOUT:
        return None, ("the audit trail goes to stdout (GPNARX_AUDIT_LOG unset or '-'): set GPNARX_AUDIT_LOG to a "
                      "file to keep a history the service can read back")
    if target.lower() == OFF:
        return None, "the audit trail is off (GPNARX_AUDIT_LOG=off): no verdict is kept"
    if "://" in target and not target.startswith("file://"):
        return None, ("the audit trail is written to an object store; the service reads a history back only "
                      "from a local file")
    return target.removeprefix("file://"), None


def lines_backwards(fh, size: int, max_bytes: int = MAX_READ_BYTES, block: int = BLOCK_BYTES):
    """Yield ``(line bytes, complete)`` of the binary file ``fh`` of ``size`` bytes, newest first, reading at
    most ``max_bytes`` of its end. The first line of what was read is yielded only when the read reached the
    file's start (otherwise it may be the tail of a longer line: it is not yielded). ``complete``: the line
    ends with a newline (the last line of a file being written may not)."""
    start = max(0, size - max_bytes)
    pos = size
    rest = b""  # the unfinished line: the bytes after the last newline seen so far
    last = True
    while pos > start:
        step = min(block, pos - start)
        pos -= step
        fh.seek(pos)
        chunk = fh.read(step) + rest
        parts = chunk.split(b"\n")
        rest = parts[0]
        for line in reversed(parts[1:]):
            if last:  # the bytes after the file's last newline: a line being written, or nothing
                last = False
                if line:
                    yield line, False
                continue
            yield line, True
        if len(rest) > MAX_LINE_BYTES:  # no newline in a long stretch: a damaged file, not an audit line
            rest = rest[-MAX_LINE_BYTES:]
    if pos == 0 and rest:
        yield rest, not last


def _number(v):
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v) if math.isfinite(v) else None


def point_of(line: dict, model: str) -> dict | None:
    """The trend point of one audit line of ``model``'s novelty verdicts, or None when the line is not one."""
    if not isinstance(line, dict) or line.get("operation") != "novelty" or line.get("model") != model:
        return None
    verdict, when = line.get("verdict"), line.get("time")
    if verdict not in VERDICTS or not isinstance(when, str):
        return None
    try:
        datetime.fromisoformat(when)
    except ValueError:
        return None
    oor = line.get("out_of_range")
    slot = line.get("slot")
    n = line.get("n_samples")
    rid = line.get("request_id")
    sha = line.get("record_sha256")
    return {"time": when, "version": str(line.get("version") or ""), "verdict": verdict,
            "score": _number(line.get("score")), "threshold": _number(line.get("threshold")),
            "n_samples": n if is_int(n) else None,
            "out_of_range": [str(x) for x in oor] if isinstance(oor, list) else [],
            "slot": slot if is_int(slot) else None,
            "request_id": rid if isinstance(rid, str) else None,
            "record_sha256": sha if isinstance(sha, str) else None}


def novelty_history(target: str | None, model: str, limit: int, max_bytes: int = MAX_READ_BYTES) -> History:
    """The last ``limit`` novelty verdicts of ``model`` in the audit trail ``target`` (oldest first), reading at
    most ``max_bytes`` of the file's end. Lines that do not parse, or are not such a verdict, are skipped:
    ``skipped_lines`` counts those that do not parse as an audit line (cut short, not JSON, wrong fields)."""
    path, why = local_path(target)
    out = History(target=shown_target(target) if (target or "").strip().lower() != OFF else OFF,
                  available=path is not None, reason=why)
    if path is None:
        return out
    try:
        fh = open(path, "rb")  # noqa: SIM115 - closed below
    except FileNotFoundError:
        out.reason = "no audit line written yet (the trail's file does not exist)"
        return out
    except OSError as exc:
        out.available, out.reason = False, f"the audit trail could not be read: {type(exc).__name__}: {exc}"[:300]
        return out
    newest_first = []
    with fh:
        size = os.fstat(fh.fileno()).st_size
        lowest = size
        for raw, complete in lines_backwards(fh, size, max_bytes):
            lowest -= len(raw) + complete
            if not raw.strip():
                continue
            try:
                line = json.loads(raw.decode("utf-8"))
            except (UnicodeDecodeError, ValueError):
                if complete:  # a line being written (no newline yet) is not counted as damaged
                    out.skipped_lines += 1
                continue
            if not isinstance(line, dict) or "operation" not in line or "model" not in line:
                out.skipped_lines += 1
                continue
            p = point_of(line, model)
            if p is not None:
                newest_first.append(p)
                if len(newest_first) >= limit:
                    break
        out.read_bytes = size - lowest
        out.older_unread = len(newest_first) < limit and size > max_bytes
    out.points = newest_first[::-1]
    if not out.points and out.reason is None:
        out.reason = f"no novelty verdict of model {model} in the audit trail's last {out.read_bytes} bytes"
    return out


__all__ = ["BLOCK_BYTES", "MAX_READ_BYTES", "History", "lines_backwards", "local_path", "novelty_history",
           "point_of"]
