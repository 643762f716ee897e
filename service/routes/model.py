"""The model card of the loaded model."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from pranet.service.deps import ModelDep
from pranet.service.schemas import ErrorResponse

router = APIRouter(tags=["model"])


@router.get(
    "/model",
    summary="The loaded model's card (name, version, action table, schedule, training metrics)",
    responses={503: {"model": ErrorResponse, "description": "model not loaded"}},
)
def model_card(model: ModelDep) -> dict[str, Any]:
    return {**model.card, "sha256": model.sha256}
