"""Values inside an evaluation and the shape rule that combines them ("Shapes" in :mod:`pipelines.expressions`).

A value is *elementwise* (a float64 scalar or a ``(B,)`` array) or a *vector* of ``k`` components, shape
``(k, B)``. A compiled sub-expression (:class:`Node`) carries its evaluator and, statically, which of the two it
is (``lead``); :func:`broadcast_lead` is the rule for combining operands.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["Value", "Env", "Evaluator", "Batch", "Assembler", "Node", "broadcast_lead", "truth", "as_float"]

#: A value inside an evaluation: a float64 scalar, an elementwise ``(B,)`` array or a ``(k, B)`` vector.
Value = float | np.floating | np.ndarray
#: The arrays of one call, name -> float64 array of shape ``(dim, B)``.
Env = Mapping[str, np.ndarray]
Evaluator = Callable[[Env], Value]
#: The batch shape of one call: ``(B,)``, or several axes (see "Shapes").
Batch = tuple[int, ...]
#: Builds the output of one call, ``(out_dim, *batch)`` float64, from the arrays and the batch shape.
Assembler = Callable[[Env, Batch], np.ndarray]


@dataclass(frozen=True)
class Node:
    """A compiled sub-expression.

    Attributes
    ----------
    fn : callable
        ``fn(env)`` evaluates the sub-expression on the arrays of one call.
    lead : int or None
        ``None`` for an elementwise value (scalar or shape ``(B,)``), ``k`` for a vector of shape ``(k, B)``.
    """

    fn: Evaluator
    lead: int | None


def broadcast_lead(leads: Sequence[int | None]) -> int | None | str:
    """Combined leading dimension of operands, or the string ``"mismatch"`` if two vectors are incompatible."""
    out: int | None = None
    for lead in leads:
        if lead is None:
            continue
        if out is None or out == 1:
            out = lead
        elif lead != 1 and lead != out:
            return "mismatch"
    return out


def truth(v: Value) -> np.ndarray:
    """Elementwise truth of ``v`` (``v != 0``; NaN is true), as a bool array of the same shape."""
    return np.not_equal(v, 0.0)


def as_float(b: Value) -> np.ndarray:
    """Bool (or any numeric) array -> float64 array of the same shape."""
    return np.asarray(b, dtype=np.float64)
