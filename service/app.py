"""The FastAPI application: ``create_app(settings)`` builds it; the lifespan loads the model once per worker.

Run it with ``pranet-serve`` (which verifies the model first), or any ASGI server:
``uvicorn --factory pranet.service.app:create_app``. This module never imports torch.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse
from fastapi_offline import FastAPIOffline
from starlette.middleware.cors import CORSMiddleware

from pranet.service.middleware import ApiKeyMiddleware, BodyLimitsMiddleware
from pranet.service.registration import RequestError
from pranet.service.routes import health, model, register, viewer
from pranet.service.schemas import ENCODING, RegisterRequest, document_limits
from pranet.service.settings import Settings
from pranet.service.state import ServiceState

OPEN_PATHS = ("/health", "/")  # no API key needed: liveness and the viewer page (it asks for the key)
OPEN_PREFIXES = (viewer.STATIC_PREFIX + "/",)
# /docs (Swagger UI) and /redoc load their scripts and styles from here, not from a CDN: they work offline.
DOCS_STATIC_PREFIX = "/static-offline-docs"

DESCRIPTION = f"""
Point-cloud registration with PRANet (a learned agent of discrete rigid actions) and optional ICP.

**Frame convention**: every transform is `T_target_source` (4x4): `target ≈ R @ source + t`,
in the units of the input clouds (which may be anything: m, mm, ...).

**Clouds** are either nested lists `[[x, y, z], ...]` or the compact binary form
`{{"encoding": "{ENCODING}", "data": "<base64 of N*3 little-endian float32>"}}`.

Every answer carries a `confidence` in [0, 1] and a `status` (`converged` or `suspect`); `"init": "global"`
handles any initial rotation. A web viewer is served at `/`.
"""


def _version() -> str:
    try:
        return version("pranet")
    except PackageNotFoundError:
        return "0.0.0"


def _error(status: int, detail: Any, headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse({"detail": detail}, status_code=status, headers=headers)


async def _request_error(_: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestError)
    return _error(exc.status, exc.detail, {"Retry-After": "1"} if exc.status == 503 else None)


async def _validation_error(_: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    errors = [{k: e[k] for k in ("type", "loc", "msg") if k in e} for e in exc.errors()]
    return _error(422, errors)


async def _unexpected_error(_: Request, exc: Exception) -> JSONResponse:
    # Starlette re-raises after this answer, so the server logs the traceback; the client gets none.
    return _error(500, "internal server error")


def _body_limit_hint(settings: Settings) -> str:
    """How the body limit was set and how to get under it, for the 413's message."""
    if settings.max_body_bytes is not None:
        origin = "PRANET_MAX_BODY_BYTES"
    else:
        origin = f"two clouds of PRANET_MAX_POINTS={settings.max_points:,} points base64-encoded"
    return (
        f"the limit is {origin}. Send clouds base64-encoded (pranet-client does above 5000 points; a JSON list "
        "costs 2-4x the bytes), downsample them, or raise the server's limits"
    )


def _custom_openapi(app: FastAPI, settings: Settings) -> dict[str, Any]:
    """FastAPI's schema plus the request body of /register (parsed by hand, in a worker thread)."""
    if app.openapi_schema:
        return app.openapi_schema
    schema = get_openapi(
        title=app.title, version=app.version, description=app.description, routes=app.routes, tags=app.openapi_tags
    )
    components = schema.setdefault("components", {})
    schemas = components.setdefault("schemas", {})
    request_schema = RegisterRequest.model_json_schema(ref_template="#/components/schemas/{model}")
    schemas.update(request_schema.pop("$defs", {}))
    schemas["RegisterRequest"] = request_schema
    state = getattr(app.state, "service", None)  # set by the lifespan, before the first request
    model = state.model if state is not None else None
    n_scales = len(model.schedule) if model is not None else None
    document_limits(schemas, settings.max_points, settings.max_list_points, n_scales)
    if settings.api_key:
        components["securitySchemes"] = {"BearerAuth": {"type": "http", "scheme": "bearer"}}
        for path, operations in schema.get("paths", {}).items():
            if path not in OPEN_PATHS:
                for operation in operations.values():
                    operation["security"] = [{"BearerAuth": []}]
                    operation.setdefault("responses", {})["401"] = {"description": "missing or invalid API key"}
    app.openapi_schema = schema
    return schema


def create_app(settings: Settings | None = None) -> FastAPI:
    """The app for ``settings`` (default: read from ``PRANET_*`` environment variables)."""
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        state = ServiceState(settings)
        state.load()  # the engine, once per worker; a failure leaves /ready at 503 with the reason
        app.state.service = state
        yield

    app = FastAPIOffline(
        title="PRANet registration service",
        version=_version(),
        description=DESCRIPTION,
        lifespan=lifespan,
        debug=False,
        static_url=DOCS_STATIC_PREFIX,
    )
    app.state.settings = settings
    for router in (health.router, model.router, register.router, viewer.router):
        app.include_router(router)
    viewer.mount_static(app)
    app.add_exception_handler(RequestError, _request_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(Exception, _unexpected_error)
    # Middlewares: the last added runs first. Order on the way in: CORS -> API key -> body size.
    app.add_middleware(
        BodyLimitsMiddleware,
        max_bytes=settings.body_limit_bytes,
        timeout_s=settings.body_timeout_s,
        hint=_body_limit_hint(settings),
    )
    if settings.api_key:
        app.add_middleware(
            ApiKeyMiddleware, api_key=settings.api_key, open_paths=OPEN_PATHS, open_prefixes=OPEN_PREFIXES
        )
    if settings.cors_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_origins,
            allow_methods=["GET", "POST"],
            allow_headers=["Authorization", "Content-Type"],
        )
    app.openapi = lambda: _custom_openapi(app, settings)  # type: ignore[method-assign]
    return app
