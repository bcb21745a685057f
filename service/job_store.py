"""The job store: jobs, their status, timestamps and progress events in SQL (SQLAlchemy 2).

An SQLite file by default (WAL mode, so the API's readers never wait for the job processes' writes), any
SQLAlchemy URL otherwise (``postgresql+psycopg://...`` for a shared deployment). Everything the API shows is
read from here, so it survives an API restart.

Tables
------
``jobs``
    One row per job: id, name, status, the validated spec (JSON), timestamps, error, the per-stage latest
    progress (``stages``, so a job's JSON is one row), the report's summary and figure names, the cancel
    request, the number of starts (``attempts``) and ``last_seq``, the number of its last event; ``owner``, which
    token submitted it (:func:`service.settings.token_owner`: a hash, never the token), for the fair queue.
``events``
    ``(job_id, seq)``: ``seq`` counts 1, 2, 3, ... per job and is the SSE event id; ``kind`` is ``progress``
    (data ``{stage, done, total, message}``) or ``status`` (data: the job's JSON at that moment).

Writes come from the API (submissions, cancels, the supervisor's status changes) and from each job's own process
(progress, its outcome): one engine per process, one short session per write, and one lock that serialises writes
in this process. Between processes, SQLite's write lock does: every write transaction starts with ``BEGIN
IMMEDIATE`` (it takes the lock before reading the row it changes, so the per-job ``seq`` is read and incremented
under it, and a writer waits up to ``busy_timeout`` instead of failing on a snapshot another process changed).
"""

from __future__ import annotations

import builtins
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from enum import Enum
from pathlib import Path
from typing import Any, overload

from sqlalchemy import (
    JSON,
    Boolean,
    DateTime,
    ForeignKey,
    Integer,
    String,
    Text,
    create_engine,
    event,
    func,
    inspect,
    select,
    text,
)
from sqlalchemy.engine import Engine, make_url
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column
from sqlalchemy.pool import StaticPool

from service.errors import JobNotFound


class JobStatus(str, Enum):
    """A job's status: queued, running, then one of the terminal succeeded, failed or cancelled.

    The values are the strings the API shows and the job store's ``status`` column holds.
    """

    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"

    def __str__(self) -> str:  # the value, in messages and f-strings alike (not "JobStatus.FAILED")
        return self.value


#: The statuses a job never leaves.
TERMINAL = frozenset({JobStatus.SUCCEEDED, JobStatus.FAILED, JobStatus.CANCELLED})
#: The statuses that hold a place in the queue (``max_concurrent_jobs``).
ACTIVE = frozenset({JobStatus.QUEUED, JobStatus.RUNNING})


def _values(statuses: Iterable[JobStatus | str]) -> list[str]:
    """The column values of ``statuses`` (``ValueError`` for a string that is no status)."""
    return [JobStatus(s).value for s in statuses]


def utcnow() -> datetime:
    return datetime.now(timezone.utc)


@overload
def _utc(dt: datetime) -> datetime: ...


@overload
def _utc(dt: None) -> None: ...


def _utc(dt: datetime | None) -> datetime | None:
    # SQLite keeps no time zone: every stored time is UTC, so attach it on the way out.
    if dt is None or dt.tzinfo is not None:
        return dt
    return dt.replace(tzinfo=timezone.utc)


class Base(DeclarativeBase):
    pass


class JobRow(Base):
    __tablename__ = "jobs"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    name: Mapped[str] = mapped_column(String(256))
    status: Mapped[str] = mapped_column(String(16), index=True)
    spec: Mapped[str] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), index=True)
    started_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    dask_dashboard: Mapped[str | None] = mapped_column(String(512), nullable=True)
    stages: Mapped[dict] = mapped_column(JSON, default=dict)
    summary: Mapped[dict | None] = mapped_column(JSON, nullable=True)
    figures: Mapped[list] = mapped_column(JSON, default=list)
    last_seq: Mapped[int] = mapped_column(Integer, default=0)
    owner: Mapped[str] = mapped_column(String(64), default="", server_default="")


class EventRow(Base):
    __tablename__ = "events"

    job_id: Mapped[str] = mapped_column(String(32), ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True)
    seq: Mapped[int] = mapped_column(Integer, primary_key=True)
    kind: Mapped[str] = mapped_column(String(16))
    data: Mapped[dict] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))


@dataclass(frozen=True)
class JobRecord:
    """A job row as a plain value (no session attached), safe to pass between threads."""

    id: str
    name: str
    status: JobStatus
    spec: str
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    error: str | None
    cancel_requested: bool
    attempts: int
    dask_dashboard: str | None
    stages: dict[str, dict[str, Any]] = field(default_factory=dict)
    summary: dict[str, Any] | None = None
    figures: list[str] = field(default_factory=list)
    last_seq: int = 0
    owner: str = ""

    @property
    def terminal(self) -> bool:
        return self.status in TERMINAL

    @classmethod
    def of(cls, row: JobRow) -> JobRecord:
        return cls(
            id=row.id, name=row.name, status=JobStatus(row.status), spec=row.spec, created_at=_utc(row.created_at),
            started_at=_utc(row.started_at), finished_at=_utc(row.finished_at), error=row.error,
            cancel_requested=bool(row.cancel_requested), attempts=row.attempts or 0, dask_dashboard=row.dask_dashboard,
            stages=dict(row.stages or {}), summary=row.summary, figures=list(row.figures or []),
            last_seq=row.last_seq or 0, owner=row.owner or "",
        )


@dataclass(frozen=True)
class QueuedJob:
    """What the queue needs of a queued job (its spec stays in the database)."""

    id: str
    owner: str
    created_at: datetime


@dataclass(frozen=True)
class EventRecord:
    seq: int
    kind: str
    data: dict[str, Any]


#: Execution option of the engine that writes: its transactions begin with ``BEGIN IMMEDIATE`` on SQLite.
_WRITE = "compabs_write"


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    # The driver's own transaction handling off: _sqlite_begin emits BEGIN (SQLAlchemy's documented recipe).
    dbapi_connection.isolation_level = None
    cur = dbapi_connection.cursor()
    # WAL: readers (the API) never block on the writer (a job process) and vice versa. NORMAL sync is safe with
    # WAL (a power cut may lose the last commits, never corrupt the file). busy_timeout covers a second process
    # (an admin's sqlite3 shell) holding the write lock for a moment.
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.execute("PRAGMA busy_timeout=10000")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.close()


def _sqlite_begin(conn: Any) -> None:
    # Reads: a deferred transaction (a consistent snapshot, no lock). Writes: the write lock first, waiting for
    # another process's write (the job processes write progress while the API writes statuses).
    conn.exec_driver_sql("BEGIN IMMEDIATE" if conn.get_execution_options().get(_WRITE) else "BEGIN")


class JobStore:
    """Jobs and events in an SQL database.

    Parameters
    ----------
    url : str
        SQLAlchemy URL. ``sqlite:///PATH`` creates ``PATH``'s directory; ``sqlite://`` is an in-memory store
        (tests).
    snapshot : callable
        ``snapshot(JobRecord) -> dict``: the job's JSON, stored as the data of each ``status`` event.

    Raises
    ------
    ValueError
        For a URL SQLAlchemy cannot parse or whose driver is not installed.
    """

    def __init__(self, url: str, snapshot: Callable[[JobRecord], dict[str, Any]]) -> None:
        try:
            u = make_url(url)
        except Exception as exc:  # ArgumentError: say which setting is wrong
            raise ValueError(f"db_url {url!r} is not an SQLAlchemy URL: {exc}") from None
        self._snapshot = snapshot
        self._lock = threading.RLock()
        # Newest event number per job written by this process: lets event streams skip queries while idle.
        self._seq: dict[str, int] = {}
        kwargs: dict[str, Any] = {}
        if u.get_backend_name() == "sqlite":
            kwargs["connect_args"] = {"check_same_thread": False}
            if not u.database or u.database == ":memory:":
                kwargs["poolclass"] = StaticPool  # one shared connection, or each would see its own empty DB
            else:
                Path(u.database).parent.mkdir(parents=True, exist_ok=True)
        try:
            self.engine: Engine = create_engine(u, **kwargs)
        except Exception as exc:  # a missing DB driver (NoSuchModuleError, ImportError)
            raise ValueError(f"db_url {u.render_as_string(hide_password=True)}: {exc}") from None
        if u.get_backend_name() == "sqlite":
            event.listen(self.engine, "connect", _sqlite_pragmas)
            event.listen(self.engine, "begin", _sqlite_begin)
        self._writer: Engine = self.engine.execution_options(**{_WRITE: True})
        Base.metadata.create_all(self._writer)
        self._add_missing_columns()

    def _add_missing_columns(self) -> None:
        # A store written before a column existed keeps its jobs: the column is added with its default
        # (create_all creates missing tables only).
        present = {c["name"] for c in inspect(self._writer).get_columns("jobs")}
        if "owner" not in present:
            with self._writer.begin() as conn:
                conn.execute(text("ALTER TABLE jobs ADD COLUMN owner VARCHAR(64) NOT NULL DEFAULT ''"))

    def close(self) -> None:
        self.engine.dispose()

    # ------------------------------------------------------------------ reads
    def get(self, job_id: str) -> JobRecord | None:
        with Session(self.engine) as s:
            row = s.get(JobRow, job_id)
            return None if row is None else JobRecord.of(row)

    def require(self, job_id: str) -> JobRecord:
        """The job ``job_id``.

        Raises
        ------
        JobNotFound
            When there is no such job (ids longer than 64 characters are not looked up).
        """
        rec = self.get(job_id) if len(job_id) <= 64 else None
        if rec is None:
            raise JobNotFound(job_id)
        return rec

    def list(self, limit: int = 100, statuses: Iterable[JobStatus] | None = None,
             owner: str | None = None) -> builtins.list[JobRecord]:
        """Jobs newest first (``statuses``: only those; oldest first then, for the queue; ``owner``: only its)."""
        with Session(self.engine) as s:
            q = select(JobRow)
            if owner is not None:
                q = q.where(JobRow.owner == owner)
            if statuses is not None:
                q = q.where(JobRow.status.in_(_values(statuses))).order_by(JobRow.created_at, JobRow.id)
            else:
                q = q.order_by(JobRow.created_at.desc(), JobRow.id.desc())
            return [JobRecord.of(r) for r in s.scalars(q.limit(limit))]

    def queue(self) -> builtins.list[QueuedJob]:
        """The queued jobs, oldest first, without their specs."""
        with Session(self.engine) as s:
            q = (select(JobRow.id, JobRow.owner, JobRow.created_at).where(JobRow.status == JobStatus.QUEUED.value)
                 .order_by(JobRow.created_at, JobRow.id))
            return [QueuedJob(i, o or "", _utc(c)) for i, o, c in s.execute(q)]

    def count(self, statuses: Iterable[JobStatus]) -> int:
        with Session(self.engine) as s:
            q = select(func.count()).select_from(JobRow).where(JobRow.status.in_(_values(statuses)))
            return s.scalar(q) or 0

    def events_after(self, job_id: str, seq: int, limit: int = 1000) -> builtins.list[EventRecord]:
        with Session(self.engine) as s:
            q = (select(EventRow).where(EventRow.job_id == job_id, EventRow.seq > seq)
                 .order_by(EventRow.seq).limit(limit))
            return [EventRecord(r.seq, r.kind, r.data) for r in s.scalars(q)]

    def known_seq(self, job_id: str) -> int | None:
        """The newest event number this process wrote or saw for the job (``None``: none since start)."""
        return self._seq.get(job_id)

    def refresh_seq(self, job_id: str) -> int | None:
        """Read the job's newest event number from the database into :meth:`known_seq` (events written by its job
        process); ``None`` when there is no such job."""
        with Session(self.engine) as s:
            seq = s.scalar(select(JobRow.last_seq).where(JobRow.id == job_id))
        if seq is not None:
            with self._lock:
                self._seq[job_id] = max(int(seq), self._seq.get(job_id, 0))
        return seq

    # ------------------------------------------------------------------ writes
    def _add_event(self, s: Session, row: JobRow, kind: str, data: dict[str, Any]) -> None:
        row.last_seq = (row.last_seq or 0) + 1
        s.add(EventRow(job_id=row.id, seq=row.last_seq, kind=kind, data=data, created_at=utcnow()))

    def _write(
        self, job_id: str, change: Callable[[Session, JobRow], str | None], new: JobRow | None = None
    ) -> JobRecord | None:
        """Apply ``change`` to a job row in one transaction; a ``"status"`` result adds a status event.

        With ``new`` the row is inserted first (``create``); otherwise a missing job gives ``None``.
        """
        with self._lock, Session(self._writer) as s, s.begin():
            row = new if new is not None else s.get(JobRow, job_id)
            if row is None:
                return None
            if new is not None:
                s.add(new)
                s.flush()
            if change(s, row) == "status":
                s.flush()
                self._add_event(s, row, "status", self._snapshot(JobRecord.of(row)))
            s.flush()
            rec = JobRecord.of(row)
        self._seq[job_id] = rec.last_seq
        return rec

    def create(self, job_id: str, name: str, spec_json: str, owner: str = "") -> JobRecord:
        """A new queued job of ``owner`` (:func:`service.settings.token_owner`) and its first status event."""
        row = JobRow(id=job_id, name=name, status=JobStatus.QUEUED.value, spec=spec_json, created_at=utcnow(), stages={},
                     figures=[], attempts=0, cancel_requested=False, last_seq=0, owner=owner)
        rec = self._write(job_id, lambda s, r: "status", new=row)
        assert rec is not None  # inserted, never missing
        return rec

    def set_status(
        self,
        job_id: str,
        status: JobStatus,
        *,
        error: str | None = None,
        summary: dict[str, Any] | None = None,
        figures: builtins.list[str] | None = None,
        dask_dashboard: str | None = None,
        started: bool = False,
        attempts_delta: int = 0,
    ) -> JobRecord | None:
        """Move a job to ``status`` (terminal statuses set ``finished_at``) and record a status event.

        A terminal job never changes again: the call then returns it unchanged.

        Raises
        ------
        ValueError
            For a ``status`` that is no :class:`JobStatus` value.
        """
        status = JobStatus(status)

        def change(s: Session, row: JobRow) -> str | None:
            if JobStatus(row.status) in TERMINAL:
                return None
            row.status = status.value
            row.error = error
            if started:
                row.started_at = row.started_at or utcnow()
                row.dask_dashboard = dask_dashboard
            if status in TERMINAL:
                row.finished_at = utcnow()
            if summary is not None:
                row.summary = summary
            if figures is not None:
                row.figures = list(figures)
            row.attempts = max(0, (row.attempts or 0) + attempts_delta)
            return "status"

        return self._write(job_id, change)

    def request_cancel(self, job_id: str) -> JobRecord | None:
        def change(s: Session, row: JobRow) -> None:
            row.cancel_requested = True

        return self._write(job_id, change)

    def add_progress(self, job_id: str, stage: str, done: int, total: int, message: str) -> None:
        """Record a progress event and the stage's latest progress on the job."""
        data = {"stage": stage, "done": int(done), "total": int(total), "message": message}

        def change(s: Session, row: JobRow) -> None:
            stages = dict(row.stages or {})
            stages[stage] = {"done": data["done"], "total": data["total"], "message": message}
            row.stages = stages  # a new dict: SQLAlchemy tracks assignment, not in-place mutation
            self._add_event(s, row, "progress", data)

        self._write(job_id, change)
