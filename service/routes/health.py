"""Liveness (always open) and readiness (the model is loaded)."""

from __future__ import annotations

from fastapi import APIRouter

from pranet.service.deps import ModelDep, StateDep
from pranet.service.schemas import ErrorResponse, HealthResponse, ModelInfo, ReadyResponse

router = APIRouter(tags=["health"])


@router.get("/health", response_model=HealthResponse, summary="Liveness: the process answers")
def health() -> HealthResponse:
    return HealthResponse()


@router.get(
    "/ready",
    response_model=ReadyResponse,
    summary="Readiness: the model is loaded and registrations are accepted",
    responses={503: {"model": ErrorResponse, "description": "model not loaded"}},
)
def ready(state: StateDep, model: ModelDep) -> ReadyResponse:
    admission = state.admission
    return ReadyResponse(
        model=ModelInfo(**model.info()),
        in_flight=admission.in_flight,
        max_concurrency=admission.max_concurrency,
        max_queue=admission.max_queue,
    )
