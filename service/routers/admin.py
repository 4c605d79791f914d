"""Registry administration."""
from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request

from ..answers import answer
from ..deps import RECORD_PROBLEMS, V1, StateDep
from ..schemas import ReloadResponse

router = APIRouter(prefix="/v1", tags=["admin"], dependencies=V1)


@router.post("/admin/reload", response_model=ReloadResponse, operation_id="reload",
             summary="Rescan the registry (in-flight requests keep their bundle); a scan that drops too many "
                     "versions is held unless accept_removal",
             responses={401: {"description": RECORD_PROBLEMS[401]},
                        409: {"description": "No registry folder configured"}})
async def reload(request: Request, state: StateDep, accept_removal: Annotated[bool, Query(
        description="Serve the scan even if it drops every version or more than GPNARX_REGISTRY_DROP_SHARE of "
                    "them (a deliberate removal); otherwise such a scan is held (`held`)")] = False):
    return answer(request, await state.reload(accept_removal=accept_removal))
