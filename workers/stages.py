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
    """Everything the abstraction stages produce; synthesis consumes it.

    Results only: the resources a job holds open beside them (its Dask client, the cluster connection, the audit
    running beside synthesis) are its :class:`~workers.job_session.JobSession`'s."""

    spec: JobSpec
    network: Network
    relations: dict[str, SubsystemRelation]  # by subsystem key
    interconnection: Any
    report: dict[str, Any] = field(default_factory=dict)
