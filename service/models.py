"""The API's JSON shapes, as pydantic models: the one source of the OpenAPI schema and of the job JSON.

The job spec itself is :class:`pipelines.spec.model.JobSpec` (published at ``GET /schema``).
"""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, Field

from service.job_store import JobRecord, JobStatus
from workers.job import STAGES


class ErrorDetail(BaseModel):
    """Every 4xx/5xx body: one message saying what is wrong and what to do."""

    detail: str = Field(description="what is wrong (the field, token or cap and its value) and what to do")


class StageProgress(BaseModel):
    """The latest progress of one stage."""

    stage: str = Field(description="plan, lipschitz, subsystems, interconnection, audit, synthesis or closed_loop")
    done: int
    total: int
    message: str
    fraction: float = Field(ge=0, le=1, description="done / total (0 when total is 0)")


class JobSummary(BaseModel):
    """Counts from the job's report (``GET /jobs/{id}/report`` has everything)."""

    abstract_states: int | None = Field(default=None, description="abstract states of the composed system (exact)")
    region_states: int | None = Field(default=None, description="abstract states in the target (or safe) region")
    domain_states: int | None = Field(default=None, description="states in the controller's domain")
    audit_transitions: int = Field(default=0, description="concrete transitions the audit checked")
    audit_violations: int = Field(default=0, description="transitions missing from the abstraction (must be 0)")
    closed_loop_runs: int | None = None
    closed_loop_violations: int | None = None


class Job(BaseModel):
    """A job as the API shows it."""

    id: str
    name: str
    status: JobStatus = Field(description="queued, running, then succeeded, failed or cancelled")
    created_at: datetime
    started_at: datetime | None = None
    finished_at: datetime | None = None
    error: str | None = Field(default=None, description="why the job failed")
    stages: list[StageProgress] = Field(
        default_factory=list, description="stages seen so far, in the order " + ", ".join(STAGES)
    )
    dask_dashboard: str | None = Field(default=None, description="the Dask dashboard of the cluster running it")
    figures: list[str] = Field(default_factory=list, description="figure names (GET /jobs/{id}/figures/{name}) once succeeded")
    summary: JobSummary | None = None
    queue_position: int | None = Field(
        default=None, ge=1,
        description="a queued job's place in the queue, 1 = starts next (the queue is fair between tokens, so a "
        "job of a token with fewer jobs may pass ahead); null otherwise, and in status events",
    )

    @classmethod
    def of(cls, rec: JobRecord, queue_position: int | None = None) -> Job:
        order = {s: i for i, s in enumerate(STAGES)}
        stages = []
        for name in sorted(rec.stages, key=lambda s: (order.get(s, len(order)), s)):
            p = rec.stages[name]
            done, total = int(p.get("done", 0)), int(p.get("total", 0))
            fraction = min(1.0, max(0.0, done / total)) if total > 0 else 0.0
            stages.append(StageProgress(stage=name, done=done, total=total, message=str(p.get("message", "")),
                                        fraction=fraction))
        return cls(
            id=rec.id, name=rec.name, status=rec.status, created_at=rec.created_at, started_at=rec.started_at,
            finished_at=rec.finished_at, error=rec.error, stages=stages, dask_dashboard=rec.dask_dashboard,
            figures=list(rec.figures) if rec.status == JobStatus.SUCCEEDED else [],
            summary=JobSummary.model_validate(rec.summary) if rec.summary else None,
            queue_position=queue_position if rec.status == JobStatus.QUEUED else None,
        )


def job_json(rec: JobRecord) -> dict[str, Any]:
    """The job's JSON (what ``GET /jobs/{id}`` returns), e.g. as the data of a ``status`` event."""
    return Job.of(rec).model_dump(mode="json")


def summarize(report: dict[str, Any]) -> dict[str, Any]:
    """The :class:`JobSummary` of a report, as JSON."""
    audit = report.get("audit") or {}
    closed = report.get("closed_loop") or {}
    return JobSummary(
        abstract_states=report.get("abstract_states"),
        region_states=report.get("region_states"),
        domain_states=report.get("domain_states"),
        audit_transitions=int(audit.get("transitions_checked", 0)),
        audit_violations=int(audit.get("violations", 0)),
        closed_loop_runs=closed.get("runs"),
        closed_loop_violations=closed.get("violations"),
    ).model_dump(mode="json")


class JobList(BaseModel):
    jobs: list[Job] = Field(description="newest first")


class ProgressEvent(BaseModel):
    """The data of an SSE ``progress`` event (``status`` events carry a :class:`Job`)."""

    stage: str
    done: int
    total: int
    message: str


class Health(BaseModel):
    """Liveness, for anyone (no token): nothing that locates the cluster (no scheduler address, no dashboard URL)."""

    status: Literal["ok"] = "ok"
    workers: int = Field(description="Dask workers connected now (0 in-process)")
    jobs_running: int = 0
    jobs_queued: int = 0
