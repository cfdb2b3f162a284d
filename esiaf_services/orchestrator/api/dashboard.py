"""GET /: the live dashboard, plain HTML, CSS and JavaScript shipped in the package (no CDN, no
build step: it works on an offline robot). The page holds no data; it reads the API with the
token of its own URL (``/?token=TOKEN``)."""
from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

FILES = Path(__file__).resolve().parent.parent / "dashboard"
ASSETS_PREFIX = "/dashboard"

router = APIRouter(tags=["dashboard"])


@router.get("/", include_in_schema=False)
async def dashboard() -> FileResponse:
    return FileResponse(FILES / "index.html", media_type="text/html")


def assets() -> StaticFiles:
    return StaticFiles(directory=FILES)
