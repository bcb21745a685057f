"""Event streams under limits: at most ``max_streams`` open ``GET /jobs/{id}/events`` streams in all and
``max_streams_per_client`` per client address; beyond either a 429 that names the cap (and ``Retry-After``).

One client holding 920 streams made ``GET /jobs/{id}`` time out at 60 s (each stream polls the job store from the
API's thread pool, which the plain routes share). The count is kept by an ASGI middleware around the whole
response, so a stream holds its place exactly as long as it is open, however it ends (finished, the client gone,
an error). A stream also ends once no event has come for ``stream_idle_timeout`` seconds (``routers/jobs.py``);
``EventSource`` reconnects by itself with ``Last-Event-ID`` and misses nothing.

The client is the connection's address: behind a reverse proxy every client is the proxy, and the per-client cap
is then one more total cap (raise it, or have the proxy limit its clients).
"""

from __future__ import annotations

import re
import threading
from collections import Counter

from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

#: The path of an event stream.
EVENTS_PATH = re.compile(r"/jobs/[^/]+/events")
#: Seconds a refused client is told to wait (``Retry-After``).
RETRY_AFTER = 5


class StreamLimits:
    """The open event streams, in all and per client; :meth:`acquire` takes a place or says why not."""

    def __init__(self, total: int, per_client: int) -> None:
        self.total = total
        self.per_client = per_client
        self._lock = threading.Lock()
        self._open = 0
        self._by_client: Counter[str] = Counter()

    @property
    def open(self) -> int:
        return self._open

    def acquire(self, client: str) -> str | None:
        """Take a place for ``client``; ``None`` when taken, else the refusal's message."""
        with self._lock:
            if self._by_client[client] >= self.per_client:
                return (f"this client already has {self._by_client[client]} open event streams, and this server's cap "
                        f"max_streams_per_client is {self.per_client}: close one (each EventSource is one stream), "
                        "or follow jobs with GET /jobs/{id}")
            if self._open >= self.total:
                return (f"this server has {self._open} open event streams, its cap max_streams is {self.total}: "
                        "try again later, or follow jobs with GET /jobs/{id}")
            self._open += 1
            self._by_client[client] += 1
            return None

    def release(self, client: str) -> None:
        with self._lock:
            self._open = max(0, self._open - 1)
            self._by_client[client] -= 1
            if self._by_client[client] <= 0:
                del self._by_client[client]


class StreamLimitMiddleware:
    """Counts ``GET /jobs/{id}/events`` responses while they run; answers 429 beyond :class:`StreamLimits`."""

    def __init__(self, app: ASGIApp, limits: StreamLimits) -> None:
        self.app = app
        self.limits = limits

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope.get("method") != "GET" or not EVENTS_PATH.fullmatch(scope.get("path", "")):
            await self.app(scope, receive, send)
            return
        client = (scope.get("client") or ("unknown", 0))[0]
        refusal = self.limits.acquire(client)
        if refusal is not None:
            await JSONResponse({"detail": refusal}, status_code=429,
                               headers={"Retry-After": str(RETRY_AFTER)})(scope, receive, send)
            return
        try:
            await self.app(scope, receive, send)
        finally:
            self.limits.release(client)
