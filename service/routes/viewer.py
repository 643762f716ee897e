"""The web viewer: ``GET /`` serves the page, ``/static/...`` its script, styles and the vendored three.js.

The files live in ``service/static`` (package data of ``pranet.service``); no CDN at run time. Both
paths are open without the API key: the page asks for the key and sends it with ``POST /register``.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from fastapi import APIRouter, FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

STATIC_DIR = Path(str(resources.files("pranet.service") / "static"))
STATIC_PREFIX = "/static"

router = APIRouter(tags=["viewer"])


@router.get("/", include_in_schema=False)
def viewer() -> FileResponse:
    return FileResponse(STATIC_DIR / "index.html", media_type="text/html")


def mount_static(app: FastAPI) -> None:
    """Serve ``service/static`` under ``/static`` (JavaScript with a JavaScript MIME type, as modules need)."""
    app.mount(STATIC_PREFIX, StaticFiles(directory=STATIC_DIR), name="static")
