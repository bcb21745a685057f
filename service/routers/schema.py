"""``/schema`` (the job spec's JSON Schema), the API's own OpenAPI document, and the ``/docs`` and ``/redoc`` pages.

``/docs`` (Swagger UI) and ``/redoc`` (ReDoc) are static pages (``service/static/docs.html``, ``redoc.html``)
that hold no data, served without the token like the dashboard: nothing of the request is written into them,
and their script (``static/docs.js``) fetches ``/openapi.json`` with the token the user gives (its form, or the
dashboard's). The viewers are this server's copies (:data:`DOCS_ASSETS`, from the ``fastapi-offline`` package,
served at ``/docs-assets``): the pages work on a closed network, and their Content-Security-Policy lets them load
nothing from elsewhere.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fastapi import APIRouter, Depends, HTTPException, Request
from fastapi.responses import FileResponse

from pipelines.spec.model import json_schema
from service.routers.common import AUTH_RESPONSES, require_token
from service.routers.dashboard import STATIC_DIR

router = APIRouter(dependencies=[Depends(require_token)], responses=AUTH_RESPONSES)
#: The docs pages: no token (they hold no data; the OpenAPI document they fetch needs it).
pages = APIRouter(include_in_schema=False)


def _docs_assets() -> Path | None:
    try:
        import fastapi_offline
    except ImportError:
        return None
    path = Path(fastapi_offline.__file__).resolve().parent / "static"
    return path if path.is_dir() else None


#: Swagger UI's and ReDoc's files (``swagger-ui-bundle.js``, ``swagger-ui.css``, ``redoc.standalone.js``), or
#: None when the ``fastapi-offline`` package is missing (the pages then say so).
DOCS_ASSETS = _docs_assets()
#: The docs pages load scripts, styles and the document from this server only; ReDoc's search runs in a blob worker.
DOCS_HEADERS = {
    "Content-Security-Policy": (
        "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
        "font-src 'self' data:; connect-src 'self'; worker-src 'self' blob:; object-src 'none'; base-uri 'none'; "
        "form-action 'self'; frame-ancestors 'none'"
    ),
    "Referrer-Policy": "no-referrer",
    "X-Content-Type-Options": "nosniff",
    "Cache-Control": "no-cache",
}


@router.get("/schema", tags=["schema"], response_model=dict[str, Any])
def spec_schema() -> dict[str, Any]:
    """The JSON Schema of a job spec (what ``POST /jobs`` accepts, as JSON or YAML)."""
    return json_schema()


@router.get("/openapi.json", include_in_schema=False)
def openapi(request: Request) -> dict[str, Any]:
    return request.app.openapi()


def _page(name: str) -> FileResponse:
    if DOCS_ASSETS is None:
        raise HTTPException(503, detail="the API docs pages need the package fastapi-offline (Swagger UI and ReDoc "
                            "files), which is not installed: pip install fastapi-offline; GET /openapi.json works")
    page = STATIC_DIR / name
    if not page.is_file():
        raise HTTPException(404, detail=f"the docs page is not installed ({page} is missing)")
    return FileResponse(page, media_type="text/html", headers=DOCS_HEADERS)


@pages.get("/docs")
def docs() -> FileResponse:
    return _page("docs.html")


@pages.get("/redoc")
def redoc() -> FileResponse:
    return _page("redoc.html")
