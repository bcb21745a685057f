"""Errors of the distributed runner.

All derive from :class:`pipelines.errors.CompabsError`, so the CLI prints them as one line and the API turns
them into a JSON error body, like every other error a user can cause or fix.
"""

from __future__ import annotations

from pipelines.errors import CompabsError


class StoreMismatchError(CompabsError):
    """A relation store was written for another spec (or by another version of compabs)."""


class StoreError(CompabsError):
    """A relation store cannot be read or written (permissions, full disk, unreachable URL)."""


class ClusterError(CompabsError):
    """The Dask cluster cannot be reached, has no workers, or lost a task's workers repeatedly."""


class TaskTimeoutError(CompabsError):
    """A cluster task ran longer than ``options.task_timeout`` (a black box that hangs).

    ``worker`` is the address of the worker that ran it and ``stuck`` whether the task's thread was still running
    there when the error was raised (the runner then restarts that worker to stop it).
    """

    def __init__(self, message: str, worker: str | None = None, stuck: bool = False) -> None:
        super().__init__(message)
        self.worker = worker
        self.stuck = stuck
