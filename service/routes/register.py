"""``POST /register``: one registration, parsed and computed in a worker thread under the admission gate."""

from __future__ import annotations

import time
from functools import partial

import anyio
from fastapi import APIRouter, Request
from starlette.requests import ClientDisconnect

from pranet.service.deps import StateDep
from pranet.service.registration import CloudLimits, RequestError, run_registration
from pranet.service.schemas import ErrorResponse, RegisterResponse

router = APIRouter(tags=["registration"])

_errors = {
    408: "the body did not arrive within the server's body timeout (PRANET_BODY_TIMEOUT_S)",
    413: "body larger than the server's byte limit (PRANET_MAX_BODY_BYTES, derived from PRANET_MAX_POINTS), or a cloud "
    "with more points than PRANET_MAX_POINTS (PRANET_MAX_LIST_POINTS for a JSON list); the message gives the count and "
    "the fix",
    415: "Content-Type is not application/json",
    422: "invalid request: unknown field, bad value, or a degenerate cloud (NaN/inf, < 3 points, identical or "
    "collinear points)",
    503: "model not loaded, or too many registrations in progress (retry later)",
    504: "the registration ran past the server's time limit",
}


@router.post(
    "/register",
    response_model=RegisterResponse,
    summary="Register source onto target: T_target_source with target ≈ R @ source + t",
    responses={status: {"model": ErrorResponse, "description": text} for status, text in _errors.items()},
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {"application/json": {"schema": {"$ref": "#/components/schemas/RegisterRequest"}}},
        }
    },
)
async def register_clouds(request: Request, state: StateDep) -> RegisterResponse:
    """Both clouds in any (common) units; the result comes back in the same units.

    Clouds are nested lists ``[[x, y, z], ...]`` or ``{"encoding": "base64-float32-le", "data": ...}``.
    The body is parsed in a worker thread (large clouds must not block the event loop).
    """
    settings = state.settings
    deadline = time.monotonic() + settings.request_timeout_s  # queueing counts against the deadline
    engine = state.require_engine()
    media_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media_type != "application/json":
        raise RequestError(415, f"Content-Type must be application/json, got {media_type or 'none'!r}")
    with state.admission.admit():
        try:
            body = await request.body()
        except ClientDisconnect:
            raise RequestError(400, "client disconnected while sending the body") from None
        work = partial(
            run_registration,
            body,
            engine=engine,
            model_info=state.require_model().info(),
            limits=CloudLimits(settings.max_points, settings.max_list_points),
            deadline=deadline,
            admitted_at=time.perf_counter(),
        )
        return await anyio.to_thread.run_sync(work, limiter=state.admission.limiter)
