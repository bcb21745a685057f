"""What a job holds open between its abstraction and its report: the Dask client synthesis runs on, the cluster
connection to close after synthesis, and the audit running beside synthesis.

The :class:`~workers.stages.Abstraction` record holds results only (what a stage hands to the next); these
resources belong to whoever opens them (:func:`workers.job.run_job`), which closes them whatever happens in between:
an error or a cancellation during synthesis must still stop the audit's child process and close a cluster this job
started, and must never close a client the caller passed in.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import TracebackType
from typing import TYPE_CHECKING, Any

from workers.stages import Abstraction, Progress, no_progress

if TYPE_CHECKING:
    from workers.cluster import Connection
    from workers.processes.audit_beside import BackgroundAudit


@dataclass
class JobSession:
    """The resources of one job, filled in by :func:`workers.job.abstract_job` and closed by its opener.

    Usable as a context manager: leaving it calls :meth:`close`.

    Attributes
    ----------
    client : distributed.Client, optional
        The job's Dask client, open for synthesis (its parts run on the workers, :func:`workers.control.partitioning`):
        the connection's, or the caller's (``Execution(client=...)``); ``None`` for a job run in process.
    connection : workers.cluster.Connection, optional
        The cluster connection this job opened, closed by :meth:`close`; ``None`` when the client is the caller's
        (it stays open) or the job has no cluster.
    pending_audit : BackgroundAudit, optional
        The audit started beside synthesis (:func:`workers.job.run_abstraction` with a session), until
        :meth:`finish_audit` or :meth:`cancel_audit`.
    """

    client: Any = None
    connection: Connection | None = None
    pending_audit: BackgroundAudit | None = None

    def finish_audit(self, abstraction: Abstraction, progress: Progress = no_progress) -> None:
        """Wait for the audit started beside synthesis and put its report in ``abstraction.report["audit"]`` (its
        time in ``stage_seconds``); nothing if none is pending. Raises what the audit raised (e.g. a black box that
        returned NaN on an audit sample)."""
        if self.pending_audit is None:
            return
        pending, self.pending_audit = self.pending_audit, None
        audit, seconds, waited = pending.result()
        abstraction.report["audit"] = {**audit, "beside_synthesis": True, "waited_seconds": waited}
        abstraction.report["stage_seconds"]["audit"] = seconds
        progress("audit", 1, 1, f"{audit['transitions_checked']} transitions, {audit['violations']} violations")

    def cancel_audit(self) -> None:
        """Stop an audit started beside synthesis, if one is running (idempotent)."""
        if self.pending_audit is not None:
            pending, self.pending_audit = self.pending_audit, None
            pending.cancel()

    def close(self) -> None:
        """Stop a pending audit and close the cluster connection this job opened; a caller's client stays open
        (idempotent)."""
        conn, self.connection, self.client = self.connection, None, None
        try:
            self.cancel_audit()
        finally:
            if conn is not None:
                conn.close()

    def __enter__(self) -> JobSession:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.close()


__all__ = ["JobSession"]
