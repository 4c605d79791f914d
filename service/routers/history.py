"""A model's recent novelty scores and verdicts, read back from the audit trail (``service.audit_history``).

GET /v1/models/{name}/novelty/history?limit=N: the last N verdicts of the model (every version, single calls
and batch slots), oldest first, for a trend (the /ui page draws one). The trail is read, never written, and
at most ``audit_history.MAX_READ_BYTES`` of its end per call.
"""
from __future__ import annotations

import asyncio
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request
from pydantic import BaseModel, Field

from ..answers import answer
from ..audit_history import MAX_READ_BYTES, novelty_history
from ..deps import RECORD_PROBLEMS, V1, NameP, StateDep

#: bounds of ``limit`` (points per answer)
LIMIT_DEFAULT = 200
LIMIT_MAX = 2000

router = APIRouter(prefix="/v1", tags=["models"], dependencies=V1)


class NoveltyPoint(BaseModel):
    """One novelty verdict as the audit trail holds it."""

    time: str = Field(..., description="When the answer was given: UTC, ISO 8601 with milliseconds.")
    version: str = Field(..., description="The model version that answered.")
    verdict: Literal["healthy", "novel", "unjudged"]
    score: float | None = Field(..., description="The novelty score (null when it was not a finite number).")
    threshold: float | None = Field(..., description="The threshold it was judged against (the version's).")
    n_samples: int | None = Field(..., description="Samples of the record scored.")
    out_of_range: list[str] = Field(default_factory=list, description="As in the novelty answer.")
    slot: int | None = Field(None, description="The record's index in a batch; null for a single call.")
    request_id: str | None = Field(None, description="The request's X-Request-ID.")
    record_sha256: str | None = Field(None, description="SHA-256 of the record (u then y as float64 bytes): the "
                                      "same record sent twice has the same hash.")


class NoveltyHistory(BaseModel):
    """A model's recent novelty verdicts, oldest first, from the audit trail."""

    model: str
    limit: int = Field(..., description="The most points asked for.")
    source: Literal["audit"] = Field("audit", description="Where the points come from: the audit trail "
                                     "(GPNARX_AUDIT_LOG).")
    target: str = Field(..., description="The trail read: its file, or 'stdout' / 'off' / an object-store URL "
                        "(not read back).")
    available: bool = Field(..., description="Whether the trail is a local file the service can read back.")
    reason: str | None = Field(None, description="Why there is no point (trail not a file, no line yet, no verdict "
                               "of this model in what was read); null when there are points.")
    points: list[NoveltyPoint] = Field(..., description="At most `limit` verdicts, oldest first.")
    read_bytes: int = Field(..., description="Bytes of the trail's end that were read.")
    skipped_lines: int = Field(..., description="Lines read that are not an audit line (cut short, not JSON): "
                               "skipped.")
    older_unread: bool = Field(..., description=f"True when the read stopped at its bound ({MAX_READ_BYTES} bytes "
                               "of the trail's end) before the trail's start and before `limit` points: older "
                               "verdicts may exist.")


Limit = Annotated[int, Query(ge=1, le=LIMIT_MAX, description=f"Most verdicts to return (1-{LIMIT_MAX}), the "
                                                             "newest ones.")]


@router.get("/models/{name}/novelty/history", response_model=NoveltyHistory, operation_id="novelty_history",
            summary="A model's recent novelty scores and verdicts, from the audit trail (oldest first)",
            description="The last `limit` novelty verdicts of the model (every version, single calls and batch "
                        "slots) as the audit trail (GPNARX_AUDIT_LOG) holds them: time, version, score, threshold, "
                        "verdict. Only a trail written to a local file can be read back; otherwise `available` is "
                        "false and `reason` says why. The trail is read from its end, at most "
                        f"{MAX_READ_BYTES} bytes; lines that do not parse are skipped and counted.",
            responses={k: {"description": RECORD_PROBLEMS[k]} for k in (401, 404, 422)})
async def get_novelty_history(request: Request, state: StateDep, name: NameP, limit: Limit = LIMIT_DEFAULT):
    state.lookup(name, None, build=False)  # 404 for a model the registry does not hold
    hist = await asyncio.to_thread(novelty_history, state.settings.audit_log, name, limit)
    return answer(request, {"model": name, "limit": limit, "source": "audit", **hist.as_dict()})
