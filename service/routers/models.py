"""Model metadata: the list, a model's latest version, one version (no model is built)."""
from __future__ import annotations

from fastapi import APIRouter, Request

from gpnarx.operations import default_mc_paths

from ..answers import answer, checked
from ..deps import RECORD_PROBLEMS, V1, NameP, StateDep, VersionP
from ..responses import conditional, render_json
from ..schemas import ModelDetail, ModelList
from ..state import ServiceState
from ..wire import REVALIDATE

router = APIRouter(prefix="/v1", tags=["models"], dependencies=V1)


def lags_of(m: dict) -> dict:
    return {"ny": int(m["lags"]["ny"]), "nu": int(m["lags"]["nu"])}


def summary_of(reg, name: str) -> dict:
    b = reg.entry(name)  # the manifest: listing models builds none
    m = b.manifest
    return {"name": name, "versions": reg.versions(name), "latest": b.version, "fs": b.fs,
            "units": m.get("units") or {}, "lags": lags_of(m), "novelty": isinstance(m.get("novelty"), dict)}


def detail_of(state: ServiceState, b) -> dict:
    m = b.manifest
    return {"name": b.name, "version": b.version, "versions": state.registry.versions(b.name),
            "aliases": state.registry.aliases_of(b.name),
            "created": m.get("created"), "lags": lags_of(m), "mode": m.get("mode"),
            "fs": b.fs, "units": m.get("units") or {}, "kernel": m.get("kernel") or {},
            "hyperparameters": m.get("hyperparameters") or {},
            "noise_calibration": m.get("noise_calibration"), "band_discrepancy": m.get("band_discrepancy"),
            "default_method": {op: b.default_method(op) for op in ("predict", "loops", "novelty")},
            "default_mc_paths": {op: state.settings.mc_paths_default or default_mc_paths(b, op)
                                 for op in ("predict", "loops", "novelty")},
            "n_train": m.get("n_train"),
            "training": m.get("training") or {}, "novelty": m.get("novelty"), "physics": m.get("physics") or {},
            "package_versions": m.get("package_versions") or {},
            "probe": (m.get("novelty") or {}).get("probe") if isinstance(m.get("novelty"), dict) else None}


@router.get("/models", response_model=ModelList, operation_id="list_models", summary="List the loaded models",
            responses={401: {"description": RECORD_PROBLEMS[401]}})
async def list_models(request: Request, state: StateDep):
    reg = state.registry
    return answer(request, {"models": [summary_of(reg, n) for n in reg.names()]})


@router.get("/models/{name}", response_model=ModelDetail, operation_id="get_model",
            summary="Metadata of a model's latest version (lags, fs, units, kernel, training metrics, novelty)",
            responses={k: {"description": RECORD_PROBLEMS[k]} for k in (401, 404)})
async def get_model(request: Request, state: StateDep, name: NameP):
    return answer(request, detail_of(state, state.lookup(name, None, build=False)))


CONDITIONAL_GET = {
    304: {"description": "Not modified: the request's If-None-Match names the answer's ETag (no body)"},
}
ETAG_HEADERS = {
    "ETag": {"description": "Weak validator of the answer; send it back in If-None-Match for a 304",
             "schema": {"type": "string"}},
    "Cache-Control": {"description": "`no-cache` (revalidate: the versions and aliases listed change), "
                                     "`private, ...` when the server sets an API key", "schema": {"type": "string"}},
}


@router.get("/models/{name}/versions/{version}", response_model=ModelDetail, operation_id="get_model_version",
            summary="Metadata of one version of a model (with an ETag; If-None-Match gives 304)",
            responses={200: {"headers": ETAG_HEADERS}, **CONDITIONAL_GET,
                       **{k: {"description": RECORD_PROBLEMS[k]} for k in (401, 404)}})
async def get_model_version(request: Request, state: StateDep, name: NameP, version: VersionP):
    body = render_json(checked(request, detail_of(state, state.lookup(name, version, build=False))))
    return conditional(request, body, "application/json", REVALIDATE)
