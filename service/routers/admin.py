"""Registry administration."""
from __future__ import annotations

from fastapi import APIRouter

from ..deps import RECORD_PROBLEMS, V1, StateDep
from ..responses import JSONBytesResponse
from ..schemas import ReloadResponse

router = APIRouter(prefix="/v1", tags=["admin"], dependencies=V1)


@router.post("/admin/reload", response_model=ReloadResponse, operation_id="reload",
             summary="Rescan the registry (in-flight requests keep their bundle)",
             responses={401: {"description": RECORD_PROBLEMS[401]},
                        409: {"description": "No registry folder configured"}})
async def reload(state: StateDep):
    return JSONBytesResponse(await state.reload())
