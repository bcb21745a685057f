"""Errors raised by the method.

Every error a user can cause derives from :class:`CompabsError`; the CLI prints its message and exits
non-zero, the API turns it into a 4xx JSON body. Messages say what is wrong, where, and what to do.
"""

from __future__ import annotations


class CompabsError(Exception):
    """Base class of all user-facing errors."""


class SpecError(CompabsError):
    """A job spec is malformed or inconsistent (wrong type, empty grid, ``sigma < 1``, ...)."""


class ExpressionError(SpecError):
    """An expression is outside the whitelist or does not compile."""


class BlackBoxError(CompabsError):
    """A black box returned NaN, inf, a wrong shape, or raised."""


class LipschitzError(CompabsError):
    """A given Lipschitz constant is contradicted by the sampled data."""


class CertificationError(CompabsError):
    """An interconnection error bound cannot be certified under the declared assumptions."""
