"""Submitting, running, cancelling and resuming jobs.

Submission validates everything that can be checked without running: the body parses, the spec validates,
every expression compiles against the whitelist (``build_network``), the regions are non-empty and the caps
hold. Only then is the job stored as ``queued``, so bad input never reaches a worker.

Running: a :class:`JobManager` starts up to ``max_running`` jobs, oldest first, each in its own thread that
calls :func:`workers.job.run_job` with the API's long-lived Dask client. The thread's progress
callback persists events (throttled to one per ``PROGRESS_INTERVAL`` seconds per stage, plus each stage's
first and last) and is where cancellation happens: once the job's flag is set it raises
:class:`~workers.job.JobCancelled`, which unwinds the stage; on a cluster the runner's mapper then cancels
the job's outstanding Dask tasks.

Restart: jobs the store shows as ``running`` when an API starts were interrupted (the process died or was
stopped mid-job). :meth:`JobManager.recover` puts them back in the queue; the runner then reuses every chunk
already marked done in the job's relation store, and synthesis starts its safety fixed point from the last
iterate it stored (:mod:`workers.checkpoint_store`). A job interrupted more than ``max_resumes`` times, or whose
cancel was requested before the API died, is ended (failed, with the reason, or cancelled) instead: a job is
never left ``running`` without a thread running it.
"""

from __future__ import annotations

import json
import logging
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import Any

import yaml

from pipelines.errors import CompabsError, SpecError
from pipelines.spec.loader import load_json, load_yaml
from pipelines.spec.model import JobSpec, parse_spec
from service.errors import BadSpec, CapExceeded, NotReady, QueueFull, UnsupportedMediaType
from service.models import job_json, summarize
from service.settings import Settings
from service.store import ACTIVE, JobRecord, JobStatus, JobStore
from workers import checkpoint_store, jobdir
from workers.job import JobCancelled, run_job

log = logging.getLogger("compabs.service")

#: Seconds between stored progress events of one stage (a stage's first and last event are always stored).
PROGRESS_INTERVAL = 0.25
#: Content types read as YAML (which also reads JSON); ``application/json`` is read as JSON.
YAML_TYPES = frozenset({"application/yaml", "application/x-yaml", "text/yaml", "text/x-yaml", "text/plain"})


# ============================================================================================ submission
def _media_type(content_type: str | None) -> str:
    """The media type of a ``Content-Type`` header, lower-case; a ``charset`` other than UTF-8 is refused."""
    media, _, params = (content_type or "").partition(";")
    media = media.strip().lower()
    if media and media != "application/json" and media not in YAML_TYPES and not media.endswith("+json"):
        raise UnsupportedMediaType(media)
    for param in params.split(";"):
        key, _, value = param.partition("=")
        charset = value.strip().strip('"').lower()
        if key.strip().lower() == "charset" and charset not in ("utf-8", "utf8", "us-ascii"):
            raise UnsupportedMediaType(f"{media}; charset={charset[:40]} (the body must be UTF-8)")
    return media


def parse_body(body: bytes, content_type: str | None) -> dict[str, Any]:
    """The spec mapping of a request body: JSON for ``application/json``, else YAML (which also reads JSON).

    The bounds of :mod:`pipelines.spec.loader` hold: YAML anchors and aliases are accepted up to an expanded size
    of ``MAX_YAML_NODES`` values, integers have at most ``MAX_INT_DIGITS`` digits.

    Raises
    ------
    UnsupportedMediaType
        For a content type that is neither JSON nor YAML, or a charset other than UTF-8.
    SpecError
        For a body that does not parse or exceeds a bound, naming the line, position or path.
    """
    media = _media_type(content_type)
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SpecError(f"the body is not UTF-8 text (byte {exc.start})") from None
    try:
        if media == "application/json" or media.endswith("+json"):
            try:
                data = load_json(text)
            except json.JSONDecodeError as exc:
                raise SpecError(f"the body is not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}") from None
        else:
            try:
                data = load_yaml(text)
            except yaml.YAMLError as exc:
                raise SpecError(f"the body is not valid YAML (or JSON): {exc}") from None
    except RecursionError:
        raise SpecError("the body is nested too deeply to be a spec") from None
    if not isinstance(data, dict):
        raise SpecError(f"a spec is a mapping of fields, got {type(data).__name__}; see GET /schema")
    return data


def validate_spec(spec: JobSpec, settings: Settings) -> None:
    """Check the caps (the cost model, :mod:`pipelines.spec.costs`, with this server's settings), compile every
    expression and resolve the regions, as the job will. Nothing is evaluated but each expression's one-point
    probe, so a spec whose knobs ask for hours or gigabytes is refused before it is queued.

    Raises
    ------
    CapExceeded
        Naming the knob (the spec's field), its value and the cap exceeded (``cap``, ``limit``).
    CompabsError
        A SpecError / ExpressionError naming the field or the offending token.
    """
    from pipelines.abstraction.relation import DEFAULT_CHUNK_POINTS
    from pipelines.network import build_network
    from pipelines.spec.costs import CostError, check_costs, check_spec
    from pipelines.spec.regions import spec_regions
    from workers.executors import TASK_POINTS

    caps = settings.caps()
    try:
        check_spec(spec, caps)  # before building: replicate: 1e9 costs nothing
        network = build_network(spec, tuple(settings.allowed_modules))
        # tasks as the executor will size them: a cluster task holds TASK_POINTS evaluations
        check_costs(spec, network, caps, task_points=DEFAULT_CHUNK_POINTS if settings.in_process else TASK_POINTS)
    except CostError as exc:
        raise CapExceeded(exc.cap_name, exc.cap, exc.message) from None
    spec_regions(spec, network)


# ============================================================================================ running
@dataclass
class _Flag:
    """A running job's stop request: ``cancel`` (DELETE) ends it cancelled, ``interrupt`` (API stop) re-queues it."""

    event: threading.Event = field(default_factory=threading.Event)
    reason: str = ""
    interrupt: bool = False

    def set(self, reason: str, interrupt: bool = False) -> None:
        if not self.event.is_set():
            self.reason, self.interrupt = reason, interrupt
            self.event.set()


@dataclass
class _Running:
    thread: threading.Thread
    flag: _Flag


class JobManager:
    """The queue and the job threads of one API process.

    Parameters
    ----------
    settings : Settings
    store : JobStore
    client : distributed.Client, optional
        The long-lived Dask client jobs run on (``None`` with ``settings.in_process``).
    cluster : dict, optional
        ``workers.cluster.connect``'s info (``scheduler``, ``dashboard``, ...).
    """

    def __init__(self, settings: Settings, store: JobStore, client: Any = None, cluster: dict[str, Any] | None = None) -> None:
        self.settings = settings
        self.store = store
        self.client = client
        self.cluster = cluster or {}
        self._lock = threading.RLock()
        self._running: dict[str, _Running] = {}
        self._stopping = False

    # ------------------------------------------------------------------ submission
    def check_capacity(self) -> None:
        """Raise :class:`QueueFull` when ``max_concurrent_jobs`` jobs are queued or running."""
        active = self.store.count(ACTIVE)
        if active >= self.settings.max_concurrent_jobs:
            raise QueueFull(active, self.settings.max_concurrent_jobs)

    def submit(self, body: bytes, content_type: str | None, name: str | None = None) -> JobRecord:
        """Validate a submitted spec and queue it.

        Raises
        ------
        QueueFull
            When ``max_concurrent_jobs`` jobs are queued or running.
        NotReady
            When the manager is shutting down.
        BadSpec
            For a ``name`` that is empty or longer than 256 characters.
        UnsupportedMediaType, CapExceeded, CompabsError
            See :func:`parse_body` and :func:`validate_spec`.
        """
        self.check_capacity()  # before parsing: a full server answers at once
        spec = parse_spec(parse_body(body, content_type))
        validate_spec(spec, self.settings)
        if name is not None and not (0 < len(name) <= 256):
            raise BadSpec("query parameter name: must be 1 to 256 characters")
        job_id = uuid.uuid4().hex[:16]
        with self._lock:
            if self._stopping:
                raise NotReady("the server is shutting down; submit the job again when it is back")
            self.check_capacity()  # again under the lock: two submissions must not both take the last place
            rec = self.store.create(job_id, name or spec.name, spec.model_dump_json())
        self._kick()
        return rec

    def get(self, job_id: str) -> JobRecord:
        """The job ``job_id``; :class:`~service.errors.JobNotFound` if there is none."""
        return self.store.require(job_id)

    def cancel(self, job_id: str) -> JobRecord:
        """Cancel a job: a queued one at once; a running one once its thread stops (its Dask tasks cancelled).

        Returns the job as it is now; cancelling an ended job changes nothing.

        Raises
        ------
        JobNotFound
            When there is no such job.
        """
        with self._lock:
            rec = self.store.require(job_id)
            if rec.terminal:
                return rec
            entry = self._running.get(job_id)
            if rec.status == JobStatus.QUEUED or entry is None:  # running with no thread here: nothing to stop
                return self._end(job_id, JobStatus.CANCELLED) or rec
            self.store.request_cancel(job_id)
            entry.flag.set("cancelled by request")
            return self.store.get(job_id) or rec

    # ------------------------------------------------------------------ lifecycle
    def recover(self) -> None:
        """End or re-queue the jobs an earlier API process left ``running`` (call once, before :meth:`start`)."""
        for rec in self.store.list(limit=1_000_000, statuses=(JobStatus.RUNNING,)):
            if rec.id in self._running:
                continue
            if rec.cancel_requested:
                self._end(rec.id, JobStatus.CANCELLED)
            elif rec.attempts > self.settings.max_resumes:
                self._end(
                    rec.id, JobStatus.FAILED,
                    error=f"the API stopped {rec.attempts} times while this job was running, so it is not resumed "
                    f"again (max_resumes = {self.settings.max_resumes}); its finished chunks are kept in the job's "
                    "directory. Submit the spec again to retry, or check the server log for what stops the API.",
                )
            else:
                log.info("job %s was running when the API stopped: re-queued, it resumes from its stored chunks", rec.id)
                self.store.set_status(rec.id, JobStatus.QUEUED)

    def start(self) -> None:
        self._kick()

    def begin_shutdown(self) -> None:
        """Start no more jobs; ask running ones to stop where they can resume (they are re-queued).

        Safe to call from a signal handler: it takes no lock.
        """
        self._stopping = True
        for e in list(self._running.values()):
            e.flag.set("interrupted: the API is stopping; the job resumes when it starts again", interrupt=True)

    def shutdown(self, timeout: float = 10.0) -> None:
        """:meth:`begin_shutdown`, then wait up to ``timeout`` seconds for the job threads.

        A job still running after that stays ``running`` in the store and is resumed by the next start.
        """
        with self._lock:
            self.begin_shutdown()
            entries = list(self._running.values())
        deadline = time.monotonic() + timeout
        for e in entries:
            e.thread.join(max(0.0, deadline - time.monotonic()))

    @property
    def running_ids(self) -> list[str]:
        with self._lock:
            return list(self._running)

    def _end(self, job_id: str, status: JobStatus, **fields: Any) -> JobRecord | None:
        """End a job ``cancelled`` or ``failed``; its synthesis checkpoints go (:func:`workers.checkpoint_store.remove`:
        such a job is never resumed, and a large case's iterates take hundreds of MB). Its other files stay."""
        checkpoint_store.remove(self.settings.jobs_dir / job_id / jobdir.CHECKPOINTS)
        return self.store.set_status(job_id, status, **fields)

    def _kick(self) -> None:
        """Start queued jobs, oldest first, while fewer than ``max_running`` run."""
        with self._lock:
            while not self._stopping and len(self._running) < self.settings.max_running:
                queued = [r for r in self.store.list(limit=len(self._running) + 1, statuses=(JobStatus.QUEUED,))
                          if r.id not in self._running]
                if not queued:
                    return
                rec = queued[0]
                started = self.store.set_status(
                    rec.id, JobStatus.RUNNING, started=True, attempts_delta=1, dask_dashboard=self.cluster.get("dashboard"),
                )
                if started is None or started.status != JobStatus.RUNNING:
                    continue
                flag = _Flag()
                thread = threading.Thread(target=self._run, args=(rec.id, flag), name=f"compabs-job-{rec.id}", daemon=True)
                self._running[rec.id] = _Running(thread, flag)
                thread.start()

    # ------------------------------------------------------------------ the job thread
    def _progress(self, job_id: str, flag: _Flag):
        last: dict[str, float] = {}

        def progress(stage: str, done: int, total: int, message: str) -> None:
            if flag.event.is_set():
                raise JobCancelled(flag.reason)
            now = time.monotonic()
            if stage not in last or done <= 0 or done >= total or now - last[stage] >= PROGRESS_INTERVAL:
                last[stage] = now
                self.store.add_progress(job_id, stage, done, total, message)

        return progress

    def _run(self, job_id: str, flag: _Flag) -> None:
        try:
            self._execute(job_id, flag)
        except Exception:  # a store write failed: log it; the next start re-queues the job
            log.exception("job %s: recording its outcome failed", job_id)
        finally:
            with self._lock:
                self._running.pop(job_id, None)
            self._kick()

    def _execute(self, job_id: str, flag: _Flag) -> None:
        rec = self.store.get(job_id)
        if rec is None:
            return
        out = self.settings.jobs_dir / job_id
        try:
            spec = parse_spec(json.loads(rec.spec))
            report = run_job(
                spec, out, client=self.client, in_process=self.settings.in_process or self.client is None,
                progress=self._progress(job_id, flag), allowed_modules=tuple(self.settings.allowed_modules),
                caps=self.settings.caps(),
            )
        except Exception as exc:
            if flag.interrupt or self._stopping:
                # Stopped by (or failing because of) the API's shutdown, e.g. its Dask client closing: resume later.
                # Not counted as an attempt: the job did nothing wrong.
                log.info("job %s interrupted by the API stopping (%s); re-queued", job_id, type(exc).__name__)
                self.store.set_status(job_id, JobStatus.QUEUED, attempts_delta=-1)
            elif isinstance(exc, JobCancelled):
                self._end(job_id, JobStatus.CANCELLED)
            elif isinstance(exc, CompabsError):
                self._end(job_id, JobStatus.FAILED, error=str(exc))
            else:
                log.exception("job %s failed with an internal error", job_id)
                self._end(
                    job_id, JobStatus.FAILED,
                    error=f"internal error ({type(exc).__name__}: {exc}); the server log has the details. "
                    "Please report it with the spec.",
                )
            return
        summary = summarize(report)
        closed = report.get("closed_loop") or {}
        error = None
        if summary["audit_violations"]:
            error = (f"the audit found {summary['audit_violations']} concrete transitions missing from the abstraction "
                     "(a soundness bug); report.json in the job's directory has the details")
        elif closed.get("violations"):
            error = f"{closed['violations']} closed-loop runs violated the specification: {closed.get('first_violation')}"
        if error:
            self._end(job_id, JobStatus.FAILED, error=error, summary=summary, figures=[])
        else:
            self.store.set_status(job_id, JobStatus.SUCCEEDED, summary=summary, figures=list(report.get("figures", [])))


def new_store(settings: Settings) -> JobStore:
    """The job store of ``settings`` (``status`` events carry the job's JSON)."""
    return JobStore(settings.database_url, job_json)
