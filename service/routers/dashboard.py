"""``/``: the dashboard page (``service/static/index.html``; its assets are under ``/static``).

The page and its assets hold no data and are served without the token: the page asks for the token and sends
it with every API request (``Authorization``, or ``?token=`` for event streams and images).
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, HTTPException
from fastapi.responses import FileResponse

#: The dashboard's files.
STATIC_DIR = Path(__file__).resolve().parents[1] / "static"

router = APIRouter(tags=["dashboard"])


@router.get("/", include_in_schema=False)
def dashboard() -> FileResponse:
    page = STATIC_DIR / "index.html"
    if not page.is_file():
        raise HTTPException(404, detail=f"the dashboard page is not installed ({page} is missing)")
    return FileResponse(page, media_type="text/html")
