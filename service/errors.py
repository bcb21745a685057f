"""What the job queue and the job store refuse, as domain errors.

Each error carries a message that names the cause and the fix; none knows about HTTP. The API layer
(``service/app.py``) maps each class to its status code. A spec that does not parse or validate is a
:class:`pipelines.errors.SpecError` (or another :class:`~pipelines.errors.CompabsError`), raised by the method's
own code; the errors here are the service's: how a spec is sent, the server's caps and its state.

::

    ServiceError
    ├── UnsupportedMediaType   the body is in a format the service does not read
    ├── BadSpec                a submission the service will not queue
    │   └── CapExceeded        ... because it exceeds one of the server's caps
    ├── QueueFull              the server already holds max_concurrent_jobs jobs
    ├── NotReady               the server is not taking jobs now (shutting down)
    └── JobNotFound            no job has this id
"""

from __future__ import annotations

__all__ = [
    "BadSpec",
    "CapExceeded",
    "JobNotFound",
    "NotReady",
    "QueueFull",
    "ServiceError",
    "UnsupportedMediaType",
]


class ServiceError(Exception):
    """A request the service refuses, with a message naming the cause and the fix."""

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message


class UnsupportedMediaType(ServiceError):
    """A body sent with a content type that is neither JSON nor YAML."""

    def __init__(self, media_type: str) -> None:
        super().__init__(
            f"content type {media_type!r} is not accepted: send the spec as application/json, or as YAML with "
            "application/yaml (text/yaml, text/plain)"
        )
        self.media_type = media_type


class BadSpec(ServiceError):
    """A submission the service will not queue (the spec itself parsed and validated)."""


class CapExceeded(BadSpec):
    """A spec beyond one of the server's caps.

    Parameters
    ----------
    cap : str
        The setting's name (``max_cells``, ``max_subsystems``, ``max_expression_length``).
    limit : int
        The setting's value on this server.
    message : str
        What exceeds it, by how much, and what to change.
    """

    def __init__(self, cap: str, limit: int, message: str) -> None:
        super().__init__(message)
        self.cap = cap
        self.limit = limit


class QueueFull(ServiceError):
    """``max_concurrent_jobs`` jobs are queued or running: the cap ``cap`` is ``limit``, ``active`` are held."""

    def __init__(self, active: int, limit: int) -> None:
        super().__init__(
            f"this server has {active} queued or running jobs, its cap max_concurrent_jobs is {limit}: "
            "wait for one to finish, or cancel one (DELETE /jobs/{id})"
        )
        self.cap = "max_concurrent_jobs"
        self.limit = limit
        self.active = active


class NotReady(ServiceError):
    """The server takes no jobs now (it is shutting down); the same request succeeds once it is back."""


class JobNotFound(ServiceError, LookupError):
    """No job has the id ``job_id`` (shown cut to 64 characters)."""

    def __init__(self, job_id: str) -> None:
        super().__init__(f"no job {job_id[:64]}")
        self.job_id = job_id
