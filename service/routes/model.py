"""The model card of the loaded model."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request

from pranet.service.schemas import ErrorResponse
from pranet.service.state import ServiceState

router = APIRouter(tags=["model"])


@router.get(
    "/model",
    summary="The loaded model's card (name, version, action table, schedule, training metrics)",
    responses={503: {"model": ErrorResponse, "description": "model not loaded"}},
)
def model_card(request: Request) -> dict[str, Any]:
    state: ServiceState = request.app.state.service
    model = state.require_model()
    return {**model.card, "sha256": model.sha256}
