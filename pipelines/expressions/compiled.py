"""The result of compilation: :class:`CompiledExpression`, a callable that checks its arrays and evaluates.

A call takes one float array of shape ``(dim, B)`` (or ``(dim, *batch)``) per variable, checks names, shapes
and batch sizes, and runs the compiled evaluators under ``np.errstate(all="ignore")``; see "Shapes" in
:mod:`pipelines.expressions`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from pipelines.errors import ExpressionError
from pipelines.expressions.checks import shown
from pipelines.expressions.values import Assembler, Batch

__all__ = ["CompiledExpression"]


class CompiledExpression:
    """A compiled safe expression; call it with the variable arrays to evaluate it.

    Attributes
    ----------
    text : str
        The expression as written (read-only).
    variables : dict of str to int
        Declared variables, name -> vector dimension (a copy; read-only).

    Notes
    -----
    ``expr(x=X, u=U)`` takes float arrays of shape ``(dim, B)`` per variable and returns a new float64 array
    of shape ``(output_dim(), B)``; or arrays of shape ``(dim, *batch)`` whose batch shapes broadcast, and then
    the result has shape ``(output_dim(), *broadcast batch)``. Every variable the expression references must be
    passed; declared but unreferenced ones may be omitted. Evaluation never raises on NaN/inf (errors are
    ignored); it raises :class:`ExpressionError` only for wrong arguments (unknown or missing name, wrong
    shape, unequal ``B``, batch shapes that do not broadcast).
    """

    __slots__ = ("_text", "_variables", "_used", "_assemble", "_out_dim")

    def __init__(
        self,
        text: str,
        variables: Mapping[str, int],
        used: frozenset[str],
        assemble: Assembler,
        out_dim: int,
    ) -> None:
        self._text = text
        self._variables = dict(variables)
        self._used = used
        self._assemble = assemble
        self._out_dim = out_dim

    @property
    def text(self) -> str:
        """The expression text as given to :func:`compile_expression`."""
        return self._text

    @property
    def variables(self) -> dict[str, int]:
        """Declared variables, name -> dimension (a fresh copy on each access)."""
        return dict(self._variables)

    def output_dim(self) -> int:
        """Number of output components (rows of the result), inferred statically at compile time."""
        return self._out_dim

    def __call__(self, **arrays: np.ndarray) -> np.ndarray:
        """Evaluate on a batch.

        Parameters
        ----------
        **arrays : array_like, shape (dim, B) or (dim, *batch)
            One array per variable, keyed by variable name; all with the same batch size ``B``, or batch shapes
            that broadcast.

        Returns
        -------
        numpy.ndarray, shape (output_dim(), B) or (output_dim(), *batch), float64
        """
        env, batch = self._prepare(arrays)
        with np.errstate(all="ignore"):
            return self._assemble(env, batch)

    def constant(self) -> float:
        """The value of an expression that reads no variable (``N - 1`` over the spec's parameters).

        Raises
        ------
        ExpressionError
            The expression reads a variable, or has more than one component.
        """
        if self._used:
            raise ExpressionError(f"expression {shown(self._text)} reads {', '.join(sorted(self._used))}; "
                                  "a constant uses numbers and parameters only")
        if self._out_dim != 1:
            raise ExpressionError(f"expression {shown(self._text)} has {self._out_dim} components; a constant is "
                                  "one number")
        with np.errstate(all="ignore"):
            return float(self._assemble({}, (1,))[0, 0])

    def _prepare(self, arrays: Mapping[str, object]) -> tuple[dict[str, np.ndarray], Batch]:
        unknown = [k for k in arrays if k not in self._variables]
        if unknown:
            raise ExpressionError(
                f"expression {shown(self._text)}: unknown variable {unknown[0]!r} passed "
                f"(declared: {', '.join(self._variables)})"
            )
        missing = sorted(self._used - set(arrays))
        if missing:
            raise ExpressionError(f"expression {shown(self._text)}: variable {missing[0]!r} was not passed")
        if not arrays:
            raise ExpressionError(
                f"expression {shown(self._text)}: pass at least one variable array so the batch size is known"
            )
        env: dict[str, np.ndarray] = {}
        batch: Batch | None = None
        for name, raw in arrays.items():
            arr = _as_batch_array(self._text, name, raw, self._variables[name])
            shape = arr.shape[1:]
            if batch is not None and shape != batch:
                if len(shape) == 1 and len(batch) == 1:
                    raise ExpressionError(
                        f"expression {shown(self._text)}: variable {name!r} has batch size {shape[0]}, "
                        f"others have {batch[0]}"
                    )
                try:
                    shape = np.broadcast_shapes(batch, shape)
                except ValueError:
                    raise ExpressionError(
                        f"expression {shown(self._text)}: variable {name!r} has batch shape {arr.shape[1:]}, "
                        f"which does not broadcast with the others' {batch}"
                    ) from None
            batch = shape
            env[name] = arr
        assert batch is not None
        for name, arr in env.items():  # batch axes right-aligned, so that vectors (k, *batch) broadcast too
            if arr.ndim - 1 < len(batch):
                env[name] = arr.reshape(arr.shape[:1] + (1,) * (len(batch) + 1 - arr.ndim) + arr.shape[1:])
        return env, batch

    def __repr__(self) -> str:
        return f"CompiledExpression({self._text!r}, variables={self._variables!r}, output_dim={self._out_dim})"


def _as_batch_array(text: str, name: str, raw: Any, dim: int) -> np.ndarray:
    """``raw`` as a float64 array of shape ``(dim, B)`` or ``(dim, *batch)``, or :class:`ExpressionError`."""
    try:
        if np.iscomplexobj(raw):
            raise TypeError("complex values are not allowed")
        arr = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ExpressionError(f"expression {shown(text)}: variable {name!r} is not a real float array ({exc})") from None
    if arr.ndim < 2 or arr.shape[0] != dim:
        raise ExpressionError(
            f"expression {shown(text)}: variable {name!r} must have shape ({dim}, B), got {arr.shape}"
        )
    return arr
