"""``/schema`` (the job spec's JSON Schema) and the API's own OpenAPI document and docs page."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse

from pipelines.spec.model import json_schema
from service.routers.common import AUTH_RESPONSES, require_token

router = APIRouter(dependencies=[Depends(require_token)], responses=AUTH_RESPONSES)


@router.get("/schema", tags=["schema"], response_model=dict[str, Any])
def spec_schema() -> dict[str, Any]:
    """The JSON Schema of a job spec (what ``POST /jobs`` accepts, as JSON or YAML)."""
    return json_schema()


@router.get("/openapi.json", include_in_schema=False)
def openapi(request: Request) -> dict[str, Any]:
    return request.app.openapi()


@router.get("/docs", include_in_schema=False)
def docs(request: Request) -> HTMLResponse:
    # A browser opening /docs?token=... must send the same token when the page fetches the OpenAPI document.
    # The token echoed here has just been checked equal to the server's, so it is no injection vector.
    token = request.query_params.get("token")
    url = "/openapi.json" + (f"?token={token}" if token and request.app.state.settings.token else "")
    return get_swagger_ui_html(openapi_url=url, title="compabs API")
