"""Submitting, running, cancelling and resuming jobs.

Submission validates everything that can be checked without running, as ``compabs validate`` does: the body
parses, the spec validates, every expression compiles against the whitelist (``build_network``), the initial
states have the system's dimension, the regions are non-empty and the caps hold. Only then is the job stored as ``queued``, so bad input never reaches a worker.

Running: a :class:`JobManager` starts up to ``max_running`` jobs, each in its own process tree
(:mod:`service.supervisor`, :mod:`service.job_process`) watched by a thread of the API that only waits: the job
process writes its progress and its outcome to the job store, and the API reads them from there. DELETE stops the
job's process group (``SIGTERM``, ``SIGKILL`` after ``stop_grace`` seconds) and with it its Dask tasks (a client
that goes away releases them; a worker still running one after :data:`TASK_GRACE` seconds is restarted). Every job
has a wall-time limit (``options.time_limit``, else ``default_time_limit``, at most ``max_time_limit``): a job
past it is stopped the same way and marked failed, with the reason. Every job has a memory limit too
(``options.memory_limit``, else ``default_memory_limit``, at most ``max_memory_limit``, in MiB) on its whole process
tree (:meth:`~service.supervisor.JobProcess.memory_over`): a job over it is killed at once and marked failed with
the limit and the use measured.

The queue is fair between tokens (:func:`fair_order`): the next job to start is taken round-robin over the
tokens that have queued jobs, oldest first within a token, so one user's fifty jobs do not hold another's one
behind them all. ``GET /jobs/{id}`` shows a queued job's place in that order.

Restart: jobs the store shows as ``running`` when an API starts were interrupted (the process died or was
stopped mid-job). :meth:`JobManager.recover` kills a job process that outlived its API, then puts the jobs back
in the queue; the runner reuses every chunk already marked done in the job's relation store, and synthesis starts
its safety fixed point from the last iterate it stored (:mod:`workers.checkpoint_store`). A job interrupted more
than ``max_resumes`` times, or whose cancel was requested before the API died, is ended (failed, with the reason,
or cancelled) instead: a job is never left ``running`` without a process running it.
"""

from __future__ import annotations

import heapq
import json
import logging
import threading
import time
import uuid
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import yaml

from pipelines.errors import SpecError
from pipelines.spec.loader import load_json, load_yaml
from pipelines.spec.model import JobSpec, parse_spec
from service.errors import BadSpec, CapExceeded, JobNotFound, NotReady, QueueFull, UnsupportedMediaType
from service.job_store import ACTIVE, JobRecord, JobStatus, JobStore, QueuedJob
from service.models import job_json
from service.settings import Settings
from service.supervisor import EXIT_STOPPED, JobProcess, describe_exit, end_job, kill_orphans

log = logging.getLogger("compabs.service")

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
    """Run every check ``compabs validate`` runs (:func:`pipelines.spec.validate.validate_spec`: the network with
    every expression compiled, the cells, the initial states' dimension, the regions, the cost model's caps), with
    this server's caps and allowlist, and this server's time-limit cap. Nothing is evaluated but each expression's
    one-point probe, so a spec whose knobs ask for hours or gigabytes, or that would fail at its first stage, is
    refused before it is queued.

    Raises
    ------
    CapExceeded
        Naming the knob (the spec's field), its value and the cap exceeded (``cap``, ``limit``).
    CompabsError
        A SpecError / ExpressionError naming the field or the offending token.
    """
    from pipelines.spec.costs import CostError, check_costs
    from pipelines.spec.validate import validate_spec as validate
    from workers.executors import TASK_POINTS

    caps = settings.caps()
    try:
        # As the job's own process will (workers.job.abstract_job), then with tasks as the cluster sizes them.
        checked = validate(spec, allowed_modules=tuple(settings.allowed_modules), caps=caps)
        if not settings.in_process:
            check_costs(spec, checked.network, caps, task_points=TASK_POINTS)
    except CostError as exc:
        raise CapExceeded(exc.cap_name, exc.cap, exc.message) from None
    limit = spec.options.time_limit
    if limit is not None and limit > settings.max_time_limit:
        raise CapExceeded("max_time_limit", int(settings.max_time_limit),
                          f"options.time_limit: the job asks for {limit:g} s of wall time, and this server's cap "
                          f"max_time_limit is {settings.max_time_limit:g} s: ask for at most that, or leave it out "
                          f"(the default is {settings.default_time_limit:g} s)")
    memory = spec.options.memory_limit
    if memory is not None and memory > settings.max_memory_limit:
        raise CapExceeded("max_memory_limit", settings.max_memory_limit,
                          f"options.memory_limit: the job asks for {memory} MiB of memory, and this server's cap "
                          f"max_memory_limit is {settings.max_memory_limit} MiB: ask for at most that, or leave it "
                          f"out (the default is {settings.default_memory_limit} MiB)")


# ============================================================================================ running
#: Seconds between the supervisor's looks at a running job (its process, its stop request, its time limit, its
#: newest event for the API's event streams).
POLL = 0.2
#: Seconds a stopped cluster job's tasks may go on running on the workers before those workers are restarted.
TASK_GRACE = 5.0

#: Why the API stopped a running job: DELETE, its time limit, its memory limit, the API stopping (the job is
#: resumed later).
CANCEL, TIME_LIMIT, MEMORY_LIMIT, INTERRUPT = "cancel", "time_limit", "memory_limit", "interrupt"
#: Bytes in a MiB, the unit of the memory limits.
MIB = 1 << 20


@dataclass
class _Running:
    """A running job: its limits, its owner, its supervisor thread, its process once started, and the API's stop
    request (``memory_used``: the bytes measured when it went over its memory limit)."""

    time_limit: float
    memory_limit: int
    owner: str = ""
    memory_used: int = 0
    thread: threading.Thread | None = None
    process: JobProcess | None = None
    stop: threading.Event = field(default_factory=threading.Event)
    reason: str = ""

    def request(self, reason: str) -> None:
        if not self.stop.is_set():
            self.reason = reason
            self.stop.set()


def time_limit(spec_json: str, settings: Settings) -> float:
    """A job's wall-time limit in seconds: ``options.time_limit``, else the server's ``default_time_limit``; at
    most ``max_time_limit`` (a larger one is refused at submission)."""
    given = (json.loads(spec_json).get("options") or {}).get("time_limit")
    limit = float(given) if given else settings.default_time_limit
    return min(limit, settings.max_time_limit)


def memory_limit(spec_json: str, settings: Settings) -> int:
    """A job's memory limit in MiB: ``options.memory_limit``, else the server's ``default_memory_limit``; at most
    ``max_memory_limit`` (a larger one is refused at submission)."""
    given = (json.loads(spec_json).get("options") or {}).get("memory_limit")
    limit = int(given) if given else settings.default_memory_limit
    return min(limit, settings.max_memory_limit)


def fair_order(queued: Sequence[QueuedJob], running: Mapping[str, int] | None = None,
               last_start: Mapping[str, int] | None = None) -> list[QueuedJob]:
    """The order in which queued jobs start: round-robin over their owners (tokens), oldest first within one.

    Parameters
    ----------
    queued : sequence of QueuedJob
        Oldest first.
    running : mapping
        Jobs running now per owner.
    last_start : mapping
        Per owner, a number that grows with each start (the owner's latest); an owner without one has started
        nothing yet.

    The next job is the oldest of the owner with the fewest jobs running, then the one who started a job
    longest ago (or never), then the one whose oldest queued job is the oldest: with equal running counts, that
    is round-robin. The rest of the order is what repeated picks would give if no running job ended.
    """
    running, last = dict(running or {}), dict(last_start or {})
    by_owner: dict[str, deque[QueuedJob]] = {}
    for job in queued:
        by_owner.setdefault(job.owner, deque()).append(job)

    def key(owner: str) -> tuple[int, int, Any, str, str]:
        head = by_owner[owner][0]
        return (running.get(owner, 0), last.get(owner, -1), head.created_at, head.id, owner)

    heap = [key(owner) for owner in by_owner]
    heapq.heapify(heap)
    tick = max(last.values(), default=0)
    order = []
    while heap:
        owner = heapq.heappop(heap)[-1]
        order.append(by_owner[owner].popleft())
        tick += 1
        running[owner], last[owner] = running.get(owner, 0) + 1, tick
        if by_owner[owner]:
            heapq.heappush(heap, key(owner))
    return order


class JobManager:
    """The queue and the supervisors of the job processes of one API process.

    Up to ``max_running`` jobs run at once, each in its own process tree (:class:`~service.supervisor.JobProcess`)
    watched by a thread of this process that does nothing else: the API answers while any job computes.

    Parameters
    ----------
    settings : Settings
    store : JobStore
    client : distributed.Client, optional
        The API's Dask client (``None`` with ``settings.in_process``): ``/health`` counts its workers, and the job
        processes join its cluster (``cluster["scheduler"]``) with its credentials.
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
        #: Per owner, the tick of its latest start (fair_order's last_start).
        self._last_start: dict[str, int] = {}
        self._ticks = 0
        self._stopping = False
        self._env: dict[str, str] = {}
        if client is not None:
            from workers.cluster import credentials_env
            from workers.errors import ClusterError

            try:
                self._env = credentials_env(client)
            except ClusterError:  # no credential files (an insecure scheduler accepted on purpose): nothing to hand on
                self._env = {}

    # ------------------------------------------------------------------ submission
    def check_capacity(self) -> None:
        """Raise :class:`QueueFull` when ``max_concurrent_jobs`` jobs are queued or running."""
        active = self.store.count(ACTIVE)
        if active >= self.settings.max_concurrent_jobs:
            raise QueueFull(active, self.settings.max_concurrent_jobs)

    def submit(self, body: bytes, content_type: str | None, name: str | None = None, owner: str = "") -> JobRecord:
        """Validate a submitted spec and queue it as a job of ``owner`` (:func:`service.settings.token_owner`).

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
            rec = self.store.create(job_id, name or spec.name, spec.model_dump_json(), owner=owner)
        self._kick()
        return rec

    def get(self, job_id: str, owner: str | None = None) -> JobRecord:
        """The job ``job_id``, of ``owner`` only unless ``owner`` is ``None``.

        Raises
        ------
        JobNotFound
            When there is no such job, or it is another owner's: the same error, so that an id tells a user
            nothing about other users' jobs.
        """
        rec = self.store.require(job_id)
        if owner is not None and rec.owner != owner:
            raise JobNotFound(job_id)
        return rec

    def cancel(self, job_id: str) -> JobRecord:
        """Cancel a job: a queued one at once; a running one once its process group has been stopped (within
        ``stop_grace`` seconds plus a moment), its Dask tasks with it.

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
            if rec.status == JobStatus.QUEUED or entry is None:  # running with no process here: nothing to stop
                return end_job(self.store, self.settings, job_id, JobStatus.CANCELLED) or rec
            self.store.request_cancel(job_id)
            entry.request(CANCEL)
            return self.store.get(job_id) or rec

    # ------------------------------------------------------------------ lifecycle
    def recover(self) -> None:
        """End or re-queue the jobs an earlier API process left ``running`` (call once, before :meth:`start`),
        after killing any job process of it that is still alive."""
        kill_orphans(self.settings.data_dir / "run")
        for rec in self.store.list(limit=1_000_000, statuses=(JobStatus.RUNNING,)):
            if rec.id in self._running:
                continue
            if rec.cancel_requested:
                end_job(self.store, self.settings, rec.id, JobStatus.CANCELLED)
            elif rec.attempts > self.settings.max_resumes:
                end_job(
                    self.store, self.settings, rec.id, JobStatus.FAILED,
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
        """Start no more jobs; stop the running ones where they can resume (they are re-queued).

        Safe to call from a signal handler: it takes no lock.
        """
        self._stopping = True
        for e in list(self._running.values()):
            e.request(INTERRUPT)

    def shutdown(self, timeout: float = 10.0) -> None:
        """:meth:`begin_shutdown`, then wait up to ``timeout`` seconds for the job processes to stop.

        A job still running after that stays ``running`` in the store and is resumed by the next start.
        """
        with self._lock:
            self.begin_shutdown()
            entries = list(self._running.values())
        deadline = time.monotonic() + timeout
        for e in entries:
            if e.thread is not None:
                e.thread.join(max(0.0, deadline - time.monotonic()))

    @property
    def running_ids(self) -> list[str]:
        with self._lock:
            return list(self._running)

    def process_of(self, job_id: str) -> JobProcess | None:
        """The process running the job ``job_id`` now (``None``: it is not running here)."""
        with self._lock:
            entry = self._running.get(job_id)
            return None if entry is None else entry.process

    def _queue(self) -> list[QueuedJob]:
        """The queued jobs in the order they will start (:func:`fair_order`)."""
        with self._lock:  # a consistent picture of what runs; the store is read outside the lock
            running: dict[str, int] = {}
            for e in self._running.values():
                running[e.owner] = running.get(e.owner, 0) + 1
            ids, last_start = set(self._running), dict(self._last_start)
        return fair_order([q for q in self.store.queue() if q.id not in ids], running, last_start)

    def queue_positions(self) -> dict[str, int]:
        """Each queued job's place in the queue: 1 starts next (if no running job ends first, the rest follow in
        this order; a job submitted later by a token with fewer jobs may pass ahead)."""
        return {q.id: i for i, q in enumerate(self._queue(), start=1)}

    def _kick(self) -> None:
        """Start queued jobs in their fair order (:func:`fair_order`) while fewer than ``max_running`` run."""
        with self._lock:
            while not self._stopping and len(self._running) < self.settings.max_running:
                queue = self._queue()
                if not queue:
                    return
                rec = self.store.set_status(
                    queue[0].id, JobStatus.RUNNING, started=True, attempts_delta=1,
                    dask_dashboard=self.cluster.get("dashboard"),
                )
                if rec is None or rec.status != JobStatus.RUNNING:
                    continue
                self._ticks += 1
                self._last_start[rec.owner] = self._ticks
                entry = _Running(time_limit(rec.spec, self.settings), memory_limit(rec.spec, self.settings) * MIB,
                                 rec.owner)
                # The supervisor thread starts the process itself: a job process dies with the thread that started
                # it (PR_SET_PDEATHSIG), so that must be the thread that lives as long as the job.
                entry.thread = threading.Thread(target=self._supervise, args=(rec.id, entry),
                                                name=f"compabs-job-{rec.id}", daemon=True)
                self._running[rec.id] = entry
                entry.thread.start()

    # ------------------------------------------------------------------ the supervisor thread
    def _supervise(self, job_id: str, entry: _Running) -> None:
        try:
            self._watch(job_id, entry)
        except Exception:  # a store write failed: log it; the next start re-queues the job
            log.exception("job %s: supervising its process failed", job_id)
        finally:
            with self._lock:
                self._running.pop(job_id, None)
            self._kick()
        if entry.reason in (CANCEL, TIME_LIMIT, MEMORY_LIMIT) and self.client is not None and not self._stopping:
            from workers.cluster import stop_released_tasks

            restarted = stop_released_tasks(self.client, TASK_GRACE)
            if restarted:
                log.info("job %s: restarted workers %s, which still ran its tasks", job_id, ", ".join(restarted))

    def _watch(self, job_id: str, entry: _Running) -> None:
        code: int | None = None
        proc = None
        if not entry.stop.is_set():
            try:
                proc = JobProcess(job_id, self.settings, self.cluster.get("scheduler") if self.client else None,
                                  self._env)
            except OSError as exc:
                end_job(self.store, self.settings, job_id, JobStatus.FAILED,
                        error=f"the server could not start the job's process: {exc}")
                return
            entry.process = proc
            while code is None:
                code = proc.wait(POLL)
                self.store.refresh_seq(job_id)  # the job process's events, for the event streams
                if code is None and proc.elapsed() > entry.time_limit:
                    entry.request(TIME_LIMIT)
                used = proc.memory_over(entry.memory_limit) if code is None and not entry.stop.is_set() else None
                if used is not None:
                    entry.memory_used = used
                    entry.request(MEMORY_LIMIT)
                    code = proc.kill()  # no grace: a process over its memory would only grow meanwhile
                if code is None and entry.stop.is_set():
                    code = proc.stop(self.settings.stop_grace)
            proc.finish()
            self.store.refresh_seq(job_id)
        self._record(job_id, entry, code, proc)

    def _record(self, job_id: str, entry: _Running, code: int | None, proc: JobProcess | None) -> None:
        """The job's status after its process ended, unless the process recorded its outcome itself."""
        rec = self.store.get(job_id)
        if rec is None or rec.terminal:
            return
        stage = next(reversed(rec.stages), None) if rec.stages else None
        where = f" during stage '{stage}'" if stage else ""  # the stage a limit stopped, for its message
        if entry.reason == CANCEL or rec.cancel_requested:
            end_job(self.store, self.settings, job_id, JobStatus.CANCELLED)
        elif entry.reason == INTERRUPT or (self._stopping and code == EXIT_STOPPED):
            # Stopped by the API's shutdown: resume later. Not counted as an attempt: the job did nothing wrong.
            log.info("job %s interrupted by the API stopping; re-queued", job_id)
            self.store.set_status(job_id, JobStatus.QUEUED, attempts_delta=-1)
        elif entry.reason == TIME_LIMIT:
            end_job(self.store, self.settings, job_id, JobStatus.FAILED,
                    error=f"the job ran past its time limit of {entry.time_limit:g} s{where} and was stopped "
                    f"(options.time_limit; this server's default is {self.settings.default_time_limit:g} s, its cap "
                    f"max_time_limit {self.settings.max_time_limit:g} s). Its finished chunks are kept: submit it "
                    "again with a larger options.time_limit, or make it smaller.")
        elif entry.reason == MEMORY_LIMIT:
            end_job(self.store, self.settings, job_id, JobStatus.FAILED,
                    error=f"the job's processes used {entry.memory_used / MIB:.0f} MiB of memory{where}, over its "
                    f"memory limit of {entry.memory_limit // MIB} MiB, and were stopped (options.memory_limit; this "
                    f"server's default is {self.settings.default_memory_limit} MiB, its cap max_memory_limit "
                    f"{self.settings.max_memory_limit} MiB). Submit it again with a larger options.memory_limit, or "
                    "make it smaller.")
        else:
            how = describe_exit(code if code is not None else -1)
            tail = proc.log_tail() if proc is not None else ""
            log.error("job %s: its process ended with %s without recording an outcome; its log (%s) ends:\n%s",
                      job_id, how, proc.log_path if proc else "-", tail)
            hint = " (killed: out of memory?)" if code == -9 else ""
            end_job(self.store, self.settings, job_id, JobStatus.FAILED,
                    error=f"the job's process ended with {how}{hint} before recording an outcome; the server log "
                    "has the details. Please report it with the spec.")


def new_store(settings: Settings) -> JobStore:
    """The job store of ``settings`` (``status`` events carry the job's JSON)."""
    return JobStore(settings.database_url, job_json)
