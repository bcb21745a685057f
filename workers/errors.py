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
