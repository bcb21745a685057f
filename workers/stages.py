"""The stages of a job and what passes between them: names, progress callbacks, cancellation, the abstraction.

Shared by the orchestrator (:mod:`workers.job`), its control stages (:mod:`workers.control`) and the service,
which shows one progress bar per :class:`Stage`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

from pipelines.abstraction.relation import SubsystemRelation
from pipelines.network import Network
from pipelines.spec.costs import Caps
from pipelines.spec.model import JobSpec

Progress = Callable[[str, int, int, str], None]


class Stage(str, Enum):
    """The stages of a job, in the order it runs them (the order of progress bars and of the API's ``stages``)."""

    PLAN = "plan"
    LIPSCHITZ = "lipschitz"
    SUBSYSTEMS = "subsystems"
    INTERCONNECTION = "interconnection"
    AUDIT = "audit"
    SYNTHESIS = "synthesis"
    CLOSED_LOOP = "closed_loop"


STAGES = tuple(s.value for s in Stage)


class JobCancelled(Exception):
    """Raised by a progress callback to stop a job; deliberately not a ``CompabsError`` (not a user error)."""

    def __init__(self, reason: str = "cancelled") -> None:
        super().__init__(reason)
        self.reason = reason


def no_progress(stage: str, done: int, total: int, message: str) -> None:
    return None


@dataclass(frozen=True)
class JobPolicy:
    """What the caller of a job allows.

    Attributes
    ----------
    allowed_modules : sequence of str, optional
        Modules a ``module:function`` black box may come from (``None``: any, as on the local command line;
        ``()``: none).
    caps : Caps, optional
        The cost model's caps (:mod:`pipelines.spec.costs`) the spec is validated against before anything starts
        (``None``: the command line's, :meth:`~pipelines.spec.costs.Caps.local`; the service passes its own).
    """

    allowed_modules: Sequence[str] | None = None
    caps: Caps | None = None


@dataclass
class Abstraction:
    """Everything the abstraction stages produce; synthesis consumes it."""

    spec: JobSpec
    network: Network
    relations: dict[str, SubsystemRelation]  # by subsystem key
    interconnection: Any
    report: dict[str, Any] = field(default_factory=dict)
    pending_audit: Any = field(default=None, repr=False)  # a BackgroundAudit until finish_audit
    client: Any = field(default=None, repr=False)  # the job's Dask client, kept open for synthesis
    cluster: Any = field(default=None, repr=False)  # the Connection to close after synthesis, if this job opened it

    def close_cluster(self) -> None:
        """Close the cluster connection kept for synthesis (``abstract_job(for_synthesis=True)``), if this job
        opened it; a caller's client stays open (idempotent)."""
        conn, self.cluster, self.client = self.cluster, None, None
        if conn is not None:
            conn.close()

    def finish_audit(self, progress: Progress = no_progress) -> None:
        """Wait for an audit started beside synthesis (``run_abstraction(audit_beside=True)``) and put its report
        in ``report["audit"]``; nothing if none is pending. Raises what the audit raised (e.g. a black box that
        returned NaN on an audit sample)."""
        if self.pending_audit is None:
            return
        pending, self.pending_audit = self.pending_audit, None
        audit, seconds, waited = pending.result()
        self.report["audit"] = {**audit, "beside_synthesis": True, "waited_seconds": waited}
        self.report["stage_seconds"]["audit"] = seconds
        progress("audit", 1, 1, f"{audit['transitions_checked']} transitions, {audit['violations']} violations")

    def cancel_audit(self) -> None:
        """Stop an audit started beside synthesis, if one is running (idempotent)."""
        if self.pending_audit is not None:
            pending, self.pending_audit = self.pending_audit, None
            pending.cancel()
