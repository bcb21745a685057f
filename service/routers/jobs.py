"""``/jobs``: submit, list, show, follow (server-sent events), download results, cancel; each token its own jobs
(the operator's every job: :mod:`service.routers.common`)."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterable
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Header, HTTPException, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse
from fastapi.sse import EventSourceResponse, ServerSentEvent

from pipelines.controller_integrity import ControllerIntegrityError
from pipelines.spec.model import parse_spec
from service.job_store import TERMINAL, JobRecord, JobStatus
from service.manager import JobManager
from service.models import ErrorDetail, Job, JobList, ProgressEvent
from service.routers.common import AUTH_RESPONSES, CallerOf, FoundJob, Manager, require_token
from workers import jobdir
from workers.controller_files import controller_archive

router = APIRouter(prefix="/jobs", tags=["jobs"], dependencies=[Depends(require_token)], responses=AUTH_RESPONSES)

_NOT_FOUND: dict[int | str, dict[str, Any]] = {404: {"model": ErrorDetail, "description": "no such job (another user's job answers the same)"}}
_NOT_DONE: dict[int | str, dict[str, Any]] = {409: {"model": ErrorDetail, "description": "the job has not succeeded"}}
#: How often an idle event stream looks for new events written by this process, and, at the longest, in the DB.
_POLL, _DB_POLL = 0.1, 2.0

_SPEC_BODY = {
    "required": True,
    "description": "the job spec (schema: GET /schema) as JSON, or as YAML text",
    "content": {
        "application/json": {"schema": {"$ref": "#/components/schemas/JobSpec"}},
        "application/yaml": {"schema": {"type": "string"}},
        "text/yaml": {"schema": {"type": "string"}},
        "text/plain": {"schema": {"type": "string"}},
    },
}


class _StreamEnded(Exception):
    """A reconnecting event stream of an ended job: answered 204, which tells EventSource to stop retrying."""


def _job_dir(manager: JobManager, rec: JobRecord) -> Path:
    return manager.settings.jobs_dir / rec.id


def _succeeded(rec: JobRecord) -> None:
    if rec.status != JobStatus.SUCCEEDED:
        raise HTTPException(409, detail=f"job {rec.id} is {rec.status}, not succeeded: it has no results"
                            + (f" ({rec.error})" if rec.error else ""))


def _file(path: Path, what: str) -> Path:
    if not path.is_file():
        raise HTTPException(404, detail=f"{what} is missing from the server's data directory ({path.name})")
    return path


@router.post(
    "", status_code=201, response_model=Job, openapi_extra={"requestBody": _SPEC_BODY},
    responses={
        413: {"model": ErrorDetail, "description": "body larger than max_body_bytes"},
        415: {"model": ErrorDetail, "description": "content type neither JSON nor YAML"},
        422: {"model": ErrorDetail, "description": "invalid spec (the field or token named), or a cap exceeded"},
        429: {"model": ErrorDetail, "description": "max_concurrent_jobs jobs are queued or running"},
    },
)
async def submit_job(
    request: Request,
    manager: Manager,
    name: Annotated[
        str | None, Query(min_length=1, max_length=256, description="the job's name (default: the spec's)")
    ] = None,
) -> Job:
    """Validate a spec (expressions compiled, regions resolved, caps checked) and queue it as a job."""
    await run_in_threadpool(manager.check_capacity)  # a full server answers before reading the body
    body = await request.body()
    rec = await run_in_threadpool(manager.submit, body, request.headers.get("content-type"), name,
                                  request.state.owner)
    places = await run_in_threadpool(manager.queue_positions)
    return Job.of(rec, places.get(rec.id))


@router.get("", response_model=JobList)
def list_jobs(
    manager: Manager,
    caller: CallerOf,
    limit: Annotated[int, Query(ge=1, le=1000, description="at most this many, newest first")] = 100,
) -> JobList:
    """The caller's jobs, newest first (the operator's token: every job)."""
    records = manager.store.list(limit=limit, owner=caller.only)
    places = manager.queue_positions() if any(r.status == JobStatus.QUEUED for r in records) else {}
    return JobList(jobs=[Job.of(r, places.get(r.id)) for r in records])


@router.get("/{job_id}", response_model=Job, responses=_NOT_FOUND)
def get_job(rec: FoundJob, manager: Manager) -> Job:
    """A job: status, its place in the queue while queued, per-stage progress, summary and figures once done."""
    return Job.of(rec, manager.queue_positions().get(rec.id) if rec.status == JobStatus.QUEUED else None)


@router.delete("/{job_id}", response_model=Job, responses=_NOT_FOUND)
def cancel_job(rec: FoundJob, manager: Manager) -> Job:
    """Cancel a job. A queued one is cancelled at once; a running one is asked to stop (its cluster tasks are
    cancelled) and shows ``cancelled`` once it has. Cancelling an ended job changes nothing."""
    return Job.of(manager.cancel(rec.id))


#: ``Last-Event-ID``: an event id as this API sends them, ASCII decimal digits only (``str.isdigit`` would take
#: "²", which ``int`` refuses) and below 10^18 (ids are SQLite integers, < 2^63); anything else is a 422.
LAST_EVENT_ID_PATTERN = r"^[0-9]{1,18}$"


def _stream_start(
    rec: FoundJob,
    last_event_id: Annotated[
        str | None,
        Header(pattern=LAST_EVENT_ID_PATTERN,
               description="resume after this event id (EventSource sends it): 1 to 18 decimal digits"),
    ] = None,
) -> tuple[JobRecord, int]:
    after = int(last_event_id) if last_event_id else 0
    if after and rec.terminal and rec.last_seq <= after:
        raise _StreamEnded()
    return rec, after


@router.get(
    "/{job_id}/events", response_class=EventSourceResponse,
    responses={**_NOT_FOUND, 204: {"description": "the job has ended and the client has every event"},
               200: {"description": "``event: progress`` (data: ProgressEvent) and ``event: status`` (data: Job); "
                     "ids count 1, 2, ... per job; the stream ends after a terminal status, or after "
                     "stream_idle_timeout seconds without an event (reconnect with Last-Event-ID)"},
               429: {"model": ErrorDetail,
                     "description": "max_streams_per_client streams of this client, or max_streams in all, are open"}},
)
async def job_events(
    start: Annotated[tuple[JobRecord, int], Depends(_stream_start)], manager: Manager,
) -> AsyncIterable[ServerSentEvent]:
    """The job's events as server-sent events: all stored ones, then live ones, until it ends.

    ``progress`` events carry ``{stage, done, total, message}``, ``status`` events the job's JSON. A client that
    reconnects with ``Last-Event-ID`` gets only the events after it. A stream without an event for
    ``stream_idle_timeout`` seconds ends (``EventSource`` reconnects by itself); open streams are capped in all and
    per client (:mod:`service.streams`).
    """
    rec, after = start
    store = manager.store
    idle = manager.settings.stream_idle_timeout
    last_event = time.monotonic()
    while True:
        events = await run_in_threadpool(store.events_after, rec.id, after)
        for ev in events:
            after = ev.seq
            data = ProgressEvent(**ev.data).model_dump() if ev.kind == "progress" else ev.data
            yield ServerSentEvent(event=ev.kind, data=data, id=str(ev.seq))
            last_event = time.monotonic()
            if ev.kind == "status" and ev.data.get("status") in TERMINAL:
                return
        if events:
            continue
        now = await run_in_threadpool(store.get, rec.id)
        if now is None or (now.terminal and now.last_seq <= after):
            return
        if time.monotonic() - last_event >= idle:
            return  # idle: the client reconnects with Last-Event-ID if it still wants the job
        # Wait for news: events this process writes are announced in memory; the DB is asked at least every
        # _DB_POLL seconds in case another process wrote (a job store shared by mistake must not hang streams).
        deadline = min(time.monotonic() + _DB_POLL, last_event + idle)
        while time.monotonic() < deadline:
            known = store.known_seq(rec.id)
            if known is not None and known > after:
                break
            await asyncio.sleep(_POLL)


@router.get("/{job_id}/report", responses={**_NOT_FOUND, **_NOT_DONE, 200: {"description": "report.json"}})
def get_report(rec: FoundJob, manager: Manager) -> FileResponse:
    """The job's ``report.json`` (counts, times, audit, synthesis, closed loop)."""
    _succeeded(rec)
    return FileResponse(_file(jobdir.report_path(_job_dir(manager, rec)), "the report"), media_type="application/json")


@router.get(
    "/{job_id}/figures/{name}",
    responses={**_NOT_FOUND, **_NOT_DONE, 200: {"content": {"image/png": {}}, "description": "the figure"}},
)
def get_figure(name: str, rec: FoundJob, manager: Manager) -> FileResponse:
    """A figure the report lists (``Job.figures``)."""
    _succeeded(rec)
    # Only names the job's report lists, and only plain file names: no path from a request reaches the disk.
    if name not in rec.figures or Path(name).name != name or not name.endswith(".png"):
        raise HTTPException(404, detail=f"job {rec.id} has no figure {name[:100]!r}; its figures are {rec.figures}")
    return FileResponse(_file(_job_dir(manager, rec) / name, f"figure {name}"), media_type="image/png")


@router.get(
    "/{job_id}/controller",
    responses={**_NOT_FOUND, 200: {"content": {"application/zip": {}},
                                   "description": "controller.json and the DDDMP files it lists"},
               409: {"model": ErrorDetail, "description": "the job has not succeeded, or its stored controller files "
                     "fail their checksums or belong to another spec (the file and what differs named)"}},
)
def get_controller(rec: FoundJob, manager: Manager) -> FileResponse:
    """The controller as a zip of ``controller.json`` (grids, variable order, spec, integrity record) and the
    files it lists (``controller.dddmp``; a layered controller has ``controller.1.dddmp``, ... too; an array
    controller ``controller.npz``); ``pipelines.load_controller(DIR)`` loads the unzipped directory.

    The files are verified first, against their checksums and against the spec this job was submitted with
    (:func:`workers.controller_files.controller_archive`): a damaged or replaced controller is refused, never served."""
    _succeeded(rec)
    job_dir = _job_dir(manager, rec)
    try:
        archive = controller_archive(job_dir, parse_spec(json.loads(rec.spec)))
    except ControllerIntegrityError as exc:
        # Named relative to the job: the server's data directory is not the client's business.
        raise HTTPException(409, detail=str(exc).replace(str(job_dir), f"job {rec.id}")) from None
    if archive is None:
        spec = json.loads(rec.spec)
        why = "options.synthesis is false" if not spec.get("options", {}).get("synthesis", True) else \
            "its files are missing from the server's data directory"
        raise HTTPException(404, detail=f"job {rec.id} has no controller: {why}")
    return FileResponse(archive, media_type="application/zip", filename=f"controller-{rec.id}.zip")
