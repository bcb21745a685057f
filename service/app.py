"""The REST API: ``create_app(settings)`` returns the FastAPI application.

Routes (``service/routers/``): ``POST /jobs``, ``GET /jobs``, ``GET /jobs/{id}``, ``DELETE /jobs/{id}``,
``GET /jobs/{id}/events`` (server-sent events), ``GET /jobs/{id}/report``, ``GET /jobs/{id}/figures/{name}``,
``GET /jobs/{id}/controller``, ``GET /schema``, ``GET /health``, ``GET /`` (dashboard), ``/static/...``,
``GET /openapi.json``, and the pages ``GET /docs`` (Swagger UI) and ``GET /redoc`` (ReDoc) with their assets
under ``/docs-assets`` (this server's copies: no CDN).

The lifespan opens the job store, connects the Dask cluster (an embedded ``LocalCluster`` of
``settings.workers`` processes, or ``settings.scheduler``; none with ``settings.in_process``), re-queues the
jobs an earlier process left running (:meth:`JobManager.recover`) and starts the queue; each job runs in a
process tree of its own (:mod:`service.supervisor`), never in this process. On shutdown it stops running jobs
where they can resume, then closes the cluster. Run it in one process
(``compabs serve``): every process would start its own cluster and its own job processes.

Errors are JSON ``{"detail": "..."}`` everywhere: a spec error (any :class:`~pipelines.errors.CompabsError`)
is 422 with its message, a cap 413/422/429 naming the cap and its value, a bug 500 without a traceback. The
queue and the job store raise :mod:`service.errors`; :data:`ERROR_STATUS` is their HTTP status. Headers are
read strictly (``Content-Length``: decimal digits; ``Last-Event-ID``: see ``routers/jobs.py``); a client that
goes away before its body is in is logged as a disconnect (one INFO line), not as an error.
"""

from __future__ import annotations

import logging
import re
from collections import Counter
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any
from urllib.parse import parse_qsl, unquote_plus

import anyio
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from pipelines.errors import CompabsError
from pipelines.spec.model import JobSpec
from service.errors import BadSpec, JobNotFound, NotReady, QueueFull, ServiceError, UnsupportedMediaType
from service.manager import JobManager, new_store
from service.models import ErrorDetail
from service.routers import dashboard, health, jobs, schema
from service.routers.jobs import _StreamEnded
from service.settings import Settings
from service.streams import StreamLimitMiddleware, StreamLimits

log = logging.getLogger("compabs.service")

DESCRIPTION = """Submit compabs job specs, follow their progress, download reports, figures and controllers.

With a token set on the server (`COMPABS_TOKEN`), every route but `/health` (and the dashboard page, the `/docs`
and `/redoc` pages and their static files, which hold no data) needs `Authorization: Bearer <token>`; clients
that cannot send headers (a browser's `EventSource`, `<img src>`) may pass `?token=<token>` instead. The docs
pages ask for the token (or use the dashboard's) and send it as the header.
"""


_DIGITS = re.compile(rb"[0-9]{1,64}")
#: What an access log shows instead of a ``?token=`` value.
REDACTED = "[redacted]"


def redact_token(target: str) -> str:
    """``target`` (a path with its query string) with the value of every ``token`` query parameter replaced by
    :data:`REDACTED`, however the name is written (``tok%65n``, ``TOKEN``: Starlette decodes names before the token
    check); the rest is left as sent."""
    path, sep, query = target.partition("?")
    if not sep:
        return target
    pieces = []
    for piece in query.split("&"):
        name, eq, _ = piece.partition("=")
        if eq and unquote_plus(name).strip().lower() == "token":
            piece = f"{name}={REDACTED}"
        pieces.append(piece)
    return f"{path}?{'&'.join(pieces)}"


class RedactTokens(logging.Filter):
    """Redacts ``?token=`` values from uvicorn's access-log lines (``%s - "%s %s HTTP/%s" %d``: the third argument
    is the path with its query string), and from any other string argument that carries a query string."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple) and record.args:
            record.args = tuple(redact_token(a) if isinstance(a, str) and "?" in a else a for a in record.args)
        if isinstance(record.msg, str) and "token=" in record.msg.lower():
            record.msg = redact_token(record.msg) if "?" in record.msg else record.msg
        return True


def redact_access_logs() -> None:
    """Install :class:`RedactTokens` on uvicorn's access and error loggers (once per logger)."""
    for name in ("uvicorn.access", "uvicorn.error", "uvicorn"):
        logger = logging.getLogger(name)
        if not any(isinstance(f, RedactTokens) for f in logger.filters):
            logger.addFilter(RedactTokens())


class BodyTooLarge(Exception):
    """A request body beyond ``max_body_bytes`` (raised while it is being received)."""

    def __init__(self, limit: int) -> None:
        super().__init__(limit)
        self.limit = limit


def _too_large(limit: int) -> JSONResponse:
    return JSONResponse(
        {"detail": f"the request body exceeds this server's cap max_body_bytes = {limit} bytes"}, status_code=413,
    )


class BodyLimitMiddleware:
    """413 for bodies over ``limit`` bytes, before any of it is parsed: at once from ``Content-Length``, else
    while it streams in (chunked uploads), by failing the receive that crosses the limit. Also 422 for a query
    parameter given more than once: every parameter of the API is one value, and Starlette would silently keep
    the last of several (``?limit=1&limit=360``)."""

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app = app
        self.limit = limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        counts = Counter(name for name, _ in parse_qsl(scope.get("query_string", b"").decode("latin-1"),
                                                       keep_blank_values=True))
        repeated = sorted(n for n, c in counts.items() if c > 1)
        if repeated:
            await JSONResponse({"detail": f"query parameter {repeated[0][:40]!r} is given {counts[repeated[0]]} "
                                "times; give each parameter once"}, status_code=422)(scope, receive, send)
            return
        for key, value in scope.get("headers", ()):
            if key == b"content-length":
                # Strictly ASCII digits: int() would also take "+5", " 5", "1_000" and a 5000-digit ValueError.
                if not _DIGITS.fullmatch(value):
                    await JSONResponse({"detail": "Content-Length must be a byte count in decimal digits, got "
                                        f"{value[:40].decode('latin-1')!r}"}, status_code=400)(scope, receive, send)
                    return
                digits = value.lstrip(b"0") or b"0"  # zero-padded is still the same count
                length = int(digits) if len(digits) <= 20 else self.limit + 1
                if length > self.limit:
                    await _too_large(self.limit)(scope, receive, send)
                    return
        seen = 0

        async def limited() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:
                    raise BodyTooLarge(self.limit)
            return message

        await self.app(scope, limited, send)


#: The HTTP status of each :class:`~service.errors.ServiceError` (a subclass not listed takes its nearest base's:
#: ``CapExceeded`` is a ``BadSpec``).
ERROR_STATUS: dict[type[ServiceError], int] = {
    ServiceError: 400,
    UnsupportedMediaType: 415,
    BadSpec: 422,
    QueueFull: 429,
    NotReady: 503,
    JobNotFound: 404,
}


def status_of(exc: ServiceError) -> int:
    """The HTTP status of ``exc``: :data:`ERROR_STATUS` of its class or its nearest listed base."""
    for cls in type(exc).__mro__:
        if cls in ERROR_STATUS:
            return ERROR_STATUS[cls]
    return ERROR_STATUS[ServiceError]  # unreachable: every ServiceError has ServiceError in its MRO


def _validation_message(exc: RequestValidationError) -> str:
    parts = []
    for e in exc.errors():
        loc = ".".join(str(p) for p in e.get("loc", ()))
        parts.append(f"{loc}: {e.get('msg')}")
    return "; ".join(parts) or "invalid request"


def _install_handlers(app: FastAPI) -> None:
    @app.exception_handler(CompabsError)
    async def compabs_error(request: Request, exc: CompabsError) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=422)

    @app.exception_handler(ServiceError)
    async def service_error(request: Request, exc: ServiceError) -> JSONResponse:
        return JSONResponse({"detail": exc.message}, status_code=status_of(exc))

    @app.exception_handler(BodyTooLarge)
    async def body_too_large(request: Request, exc: BodyTooLarge) -> JSONResponse:
        return _too_large(exc.limit)

    @app.exception_handler(RequestValidationError)
    async def bad_request(request: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse({"detail": _validation_message(exc)}, status_code=422)

    @app.exception_handler(ClientDisconnect)
    async def client_disconnect(request: Request, exc: ClientDisconnect) -> Response:
        # Not a server error: the client went away before it had sent its whole body. One line, no traceback.
        client = f"{request.client.host}:{request.client.port}" if request.client else "a client"
        log.info("%s disconnected during %s %s before sending its whole body", client, request.method,
                 request.url.path)
        return Response(status_code=400)  # nobody reads it

    @app.exception_handler(_StreamEnded)
    async def stream_ended(request: Request, exc: _StreamEnded) -> Response:
        return Response(status_code=204)

    @app.exception_handler(Exception)
    async def internal_error(request: Request, exc: Exception) -> JSONResponse:
        log.error("internal error on %s %s", request.method, request.url.path, exc_info=exc)
        return JSONResponse(
            {"detail": f"internal error ({type(exc).__name__}); the server log has the details. Please report it."},
            status_code=500,
        )


def _errors_as_published(doc: dict[str, Any]) -> None:
    """Document error bodies as they are sent: every 4xx is ``ErrorDetail`` (``{"detail": "text"}``) in JSON.

    FastAPI documents 422 as its validation-error array and gives an event-stream route's errors that route's
    media type; this API answers both with :class:`ErrorDetail` JSON (schemathesis checks the two agree).
    """
    ref = {"$ref": "#/components/schemas/ErrorDetail"}
    schemas = doc.setdefault("components", {}).setdefault("schemas", {})
    schemas.setdefault("ErrorDetail", ErrorDetail.model_json_schema())
    for operations in doc.get("paths", {}).values():
        for op in operations.values():
            # Any route: a query parameter given twice (BodyLimitMiddleware) or a malformed header.
            op.setdefault("responses", {}).setdefault(
                "422", {"description": "a query parameter given more than once, or a malformed header"})
            for code, response in op.get("responses", {}).items():
                if str(code).startswith("4"):
                    response["content"] = {"application/json": {"schema": ref}}
    for name in ("HTTPValidationError", "ValidationError"):
        schemas.pop(name, None)


def _install_openapi(app: FastAPI) -> None:
    """Publish :class:`JobSpec` as the body schema of ``POST /jobs`` (read by hand for JSON and YAML alike)."""

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            doc = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
            spec = JobSpec.model_json_schema(ref_template="#/components/schemas/{model}")
            schemas = doc.setdefault("components", {}).setdefault("schemas", {})
            schemas.update(spec.pop("$defs", {}))
            schemas["JobSpec"] = spec
            _errors_as_published(doc)
            app.openapi_schema = doc
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def create_app(settings: Settings | None = None) -> FastAPI:
    """The API application.

    Parameters
    ----------
    settings : Settings, optional
        Default: :meth:`Settings.from_env` (``COMPABS_*`` variables).
    """
    settings = settings or Settings.from_env()
    redact_access_logs()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        redact_access_logs()  # again: a logging configuration applied since create_app may have replaced loggers
        from workers.cluster import remove_stale_credentials

        await anyio.to_thread.run_sync(remove_stale_credentials)  # a killed API's cluster key, say
        try:
            settings.jobs_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RuntimeError(f"cannot create the data directory {settings.jobs_dir}: {exc.strerror}; "
                               "choose another with --data or COMPABS_DATA_DIR") from None
        store = await anyio.to_thread.run_sync(new_store, settings)
        conn = None
        client, cluster = None, {"scheduler": None, "workers": 0, "dashboard": None, "embedded": False}
        try:
            if not settings.in_process:
                from workers.cluster import connect

                # A synchronous client, made off the event loop: /health and the supervisors use it with blocking calls.
                conn = await anyio.to_thread.run_sync(connect, settings.scheduler, settings.workers)
                client, cluster = conn
                log.info("Dask scheduler %s, dashboard %s", cluster["scheduler"], cluster["dashboard"])
            manager = JobManager(settings, store, client, cluster)
            await anyio.to_thread.run_sync(manager.recover)
            manager.start()
            app.state.manager = manager
            yield
            await anyio.to_thread.run_sync(manager.shutdown)
        finally:
            if conn is not None:
                await anyio.to_thread.run_sync(conn.close)
            store.close()

    app = FastAPI(
        title="compabs", version=_version(), description=DESCRIPTION, lifespan=lifespan,
        docs_url=None, redoc_url=None, openapi_url=None,  # served by routers/schema.py, behind the token
    )
    app.state.settings = settings
    app.add_middleware(BodyLimitMiddleware, limit=settings.max_body_bytes)
    app.state.streams = StreamLimits(settings.max_streams, settings.max_streams_per_client)
    app.add_middleware(StreamLimitMiddleware, limits=app.state.streams)
    _install_handlers(app)
    app.include_router(jobs.router)
    app.include_router(schema.router)
    app.include_router(schema.pages)
    app.include_router(health.router)
    app.include_router(dashboard.router)
    dashboard.STATIC_DIR.mkdir(parents=True, exist_ok=True)
    app.mount("/static", StaticFiles(directory=dashboard.STATIC_DIR), name="static")
    if schema.DOCS_ASSETS is not None:  # Swagger UI and ReDoc, served from here (no CDN)
        app.mount("/docs-assets", StaticFiles(directory=schema.DOCS_ASSETS), name="docs-assets")
    _install_openapi(app)
    return app


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("compabs")
    except Exception:  # not installed (a source checkout on sys.path)
        return "0"
