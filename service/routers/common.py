"""Dependencies the routers share: the token check (who calls), the job manager, a job of the caller's (or 404,
via :class:`~service.errors.JobNotFound` and the app's handler).

Authentication: with ``settings.token`` set, every route but ``/health`` (and the dashboard's static assets,
which hold no data) needs the token, as ``Authorization: Bearer <token>`` or, for what a browser cannot send
headers with (``EventSource``, ``<img src>``), as the query parameter
``?token=<token>``. A token in a URL can end up in proxy logs and browser history: prefer the header where a
client can set one, and serve over TLS (a reverse proxy) beyond 127.0.0.1.

Isolation between users: a user's token (``settings.tokens``) sees, reads, follows, downloads and cancels only the
jobs it submitted; another user's job answers exactly as an unknown id does (404 ``no job <id>``), so ids tell a
user nothing about other users' jobs. The operator's token (``settings.token``) sees every job, and so does every
request on a server without tokens (:class:`Caller`).
"""

from __future__ import annotations

import secrets
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request, Security
from fastapi.security import APIKeyQuery, HTTPAuthorizationCredentials, HTTPBearer

from service.job_store import JobRecord
from service.manager import JobManager
from service.models import ErrorDetail
from service.settings import token_owner

_bearer = HTTPBearer(auto_error=False, description="the server's token (COMPABS_TOKEN)")
_query = APIKeyQuery(
    name="token", auto_error=False,
    description="the server's token, for clients that cannot send headers (EventSource, <img src>)",
)

#: OpenAPI entries of the errors every protected route can answer.
AUTH_RESPONSES: dict[int | str, dict[str, Any]] = {401: {"model": ErrorDetail, "description": "missing or wrong token"}}


@dataclass(frozen=True)
class Caller:
    """Who sends a request: ``owner``, the hash of its token (:func:`~service.settings.token_owner`; ``""``
    without tokens), and whether it sees every job (the operator's token, or a server without tokens) or only
    those it submitted."""

    owner: str
    sees_all: bool

    @property
    def only(self) -> str | None:
        """The owner whose jobs this caller sees; ``None``: every job."""
        return None if self.sees_all else self.owner


def require_token(
    request: Request,
    bearer: Annotated[HTTPAuthorizationCredentials | None, Security(_bearer)],
    query: Annotated[str | None, Security(_query)],
) -> Caller:
    """401 unless the request carries one of the server's tokens (when one is set); the :class:`Caller` it names,
    also as ``request.state.owner`` (for the fair queue)."""
    settings = request.app.state.settings
    tokens = settings.accepted_tokens
    if not tokens:
        request.state.owner = token_owner(None)
        return Caller(request.state.owner, sees_all=True)
    given = bearer.credentials if bearer is not None else query
    # compare_digest, against every token: the time taken must not tell how much of a guess was right, or which.
    matches = [given is not None and secrets.compare_digest(given.encode(), t.encode()) for t in tokens]
    if not any(matches):
        what = "a wrong token" if given is not None else "no token"
        raise HTTPException(
            401,
            detail=f"this server requires a token and the request has {what}: send the header "
            "'Authorization: Bearer <token>', or add ?token=<token> to the URL",
            headers={"WWW-Authenticate": "Bearer"},
        )
    request.state.owner = token_owner(given)
    return Caller(request.state.owner, sees_all=matches[0] and settings.token is not None)


#: The caller of a request (401 without an accepted token), as a route parameter.
CallerOf = Annotated[Caller, Depends(require_token)]


def get_manager(request: Request) -> JobManager:
    manager: JobManager = request.app.state.manager
    return manager


#: The app's job manager, as a route parameter.
Manager = Annotated[JobManager, Depends(get_manager)]


def job_or_404(job_id: str, manager: Manager, caller: CallerOf) -> JobRecord:
    """The job of the path's ``job_id``; :class:`~service.errors.JobNotFound` (404) if there is none, or if it is
    another user's (the same answer: :meth:`JobManager.get`)."""
    return manager.get(job_id, owner=caller.only)


#: The caller's job named by the path's ``job_id``, as a route parameter (404 if there is none).
FoundJob = Annotated[JobRecord, Depends(job_or_404)]
