"""Black boxes: the only access the method has to the dynamics ``f_i`` and the interconnection map ``M``.

A :class:`BlackBox` evaluates a map on a batch of points and checks what comes back: the shape, and that
every value is finite. A NaN, an inf, a wrong shape or an exception becomes a :class:`BlackBoxError` naming
the black box and the offending input, never a silently wrong abstraction.

Expression black boxes travel as text (they pickle as their source) and compile where they run.
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable, Sequence

import numpy as np

from pipelines.errors import BlackBoxError, SpecError
from pipelines.spec.model import is_module_function

# Axis permutations by ndim (what np.moveaxis(a, -1, 0) and np.moveaxis(a, 0, -1) compute, without their
# ~8 us of argument normalisation per call: the per-cell stage calls the black box twice per block).
_LAST_FIRST = {k: (k - 1, *range(k - 1)) for k in range(1, 65)}
_FIRST_LAST = {k: (*range(1, k), 0) for k in range(1, 65)}


def as_rows(arrays: Sequence[np.ndarray], shape: tuple[int, ...]) -> tuple[np.ndarray, ...]:
    """Arrays of shape ``(*batch_k, d_k)`` that broadcast to ``shape`` as copies of shape ``(prod(shape), d_k)``:
    the arguments a ``module:function`` black box is written for."""
    rows = math.prod(shape)  # not -1: an argument of dimension 0 (no internal variable) has no size to divide
    return tuple(np.broadcast_to(a, shape + a.shape[-1:]).reshape(rows, a.shape[-1]) for a in arrays)


class BlackBox:
    """A vectorised map ``(arrays of shape (B, d_k)) -> array of shape (B, out_dim)``.

    The batch may also be several leading axes that broadcast (``(*batch, d_k) -> (*batch, out_dim)``): a grid
    of samples passed as broadcast views. Expressions evaluate on the views directly; a ``module:function``
    receives the materialised ``(B, d_k)`` arrays it is written for.

    Parameters
    ----------
    name : str
        Used in error messages (e.g. ``"subsystem 'tank[3]' dynamics"``).
    source : str
        A safe expression, or ``module:function`` (only where ``allowed_modules`` permits).
    inputs : dict of str to int
        Argument names and dimensions, in call order (``{"x": 1, "u": 1, "w": 1}``).
    out_dim : int or None
        Expected output dimension; ``None`` infers it from the expression.
    constants : dict of str to float
        Named numbers usable in expressions.
    allowed_modules : sequence of str or None
        Modules a ``module:function`` may come from; ``None`` allows any (local command line), ``()`` none.
    """

    def __init__(
        self,
        name: str,
        source: str,
        inputs: dict[str, int],
        out_dim: int | None = None,
        constants: dict[str, float] | None = None,
        allowed_modules: Sequence[str] | None = (),
    ) -> None:
        self._name = name
        self._source = source.strip()
        self._inputs = dict(inputs)
        self._constants = dict(constants or {})
        self._allowed = None if allowed_modules is None else tuple(allowed_modules)
        self._is_module = is_module_function(self._source)
        self._fn: Callable[..., np.ndarray] = self._compile()
        self._out_dim = out_dim if out_dim is not None else self._infer_out_dim()
        if out_dim is not None:
            got = self._infer_out_dim()
            if got != out_dim:
                raise SpecError(f"{name}: returns {got} components, expected {out_dim}")

    # -------------------------------------------------------------- construction
    def _compile(self) -> Callable[..., np.ndarray]:
        if self._is_module:
            module_name, func = self._source.split(":")
            if self._allowed is not None and not any(
                module_name == m or module_name.startswith(m + ".") for m in self._allowed
            ):
                raise SpecError(
                    f"{self._name}: module '{module_name}' is not on this server's allowlist; "
                    "use a safe expression instead"
                )
            try:
                mod = importlib.import_module(module_name)
                fn = getattr(mod, func)
            except (ImportError, AttributeError) as exc:
                raise SpecError(f"{self._name}: cannot load {self._source}: {exc}") from None
            if not callable(fn):
                raise SpecError(f"{self._name}: {self._source} is not callable")
            return fn
        else:
            from pipelines.errors import ExpressionError
            from pipelines.expressions import compile_expression

            # An argument of dimension 0 (a subsystem that reads no internal variable) is not a variable.
            used = {k: d for k, d in self._inputs.items() if d > 0}
            try:
                expr = compile_expression(self._source, used, self._constants)
            except ExpressionError as exc:  # name the field as well as the token
                raise ExpressionError(f"{self._name}: {exc}") from None

            def run(*arrays: np.ndarray) -> np.ndarray:
                # (*batch, d) -> (d, *batch) views in; (out, *batch) -> (*batch, out) view back
                out = expr(**{k: a.transpose(_LAST_FIRST[a.ndim]) for k, a in zip(self._inputs, arrays) if k in used})
                out = np.asarray(out, dtype=float)
                return out.transpose(_FIRST_LAST[out.ndim])

            return run

    def _infer_out_dim(self) -> int:
        probe = [np.ones((1, d)) for d in self._inputs.values()]
        try:
            with np.errstate(all="ignore"):
                out = np.asarray(self._fn(*probe))
        except Exception as exc:  # a user function may raise anything
            raise BlackBoxError(f"{self._name}: raised {type(exc).__name__}: {exc}") from None
        if out.ndim != 2 or out.shape[0] != 1:
            raise BlackBoxError(f"{self._name}: returned shape {out.shape} for a batch of 1, expected (1, d)")
        return int(out.shape[1])

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_fn"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._fn = self._compile()

    # -------------------------------------------------------------- properties
    @property
    def name(self) -> str:
        return self._name

    @property
    def source(self) -> str:
        return self._source

    @property
    def out_dim(self) -> int:
        return self._out_dim

    @property
    def inputs(self) -> dict[str, int]:
        return dict(self._inputs)

    # -------------------------------------------------------------- evaluation
    def __call__(self, *arrays: np.ndarray, describe: Callable[[int], str] | None = None) -> np.ndarray:
        """Evaluate on a batch.

        Parameters
        ----------
        *arrays : ndarray, shape (B, d_k) or (*batch_k, d_k)
            One per input, in the order of ``inputs``; the ``batch_k`` broadcast to one batch shape.
        describe : callable, optional
            Maps a batch row (flat, row-major over the batch shape) to a description (e.g. the cell it was
            sampled in) for error messages.

        Returns
        -------
        ndarray, shape (B, out_dim) or (*batch, out_dim), float64, all finite.
        """
        shape = self._batch_shape(arrays)
        out = self._evaluate(arrays, shape, describe)
        self._check_finite(out, shape, arrays, describe)
        return out

    def _batch_shape(self, arrays: Sequence[np.ndarray]) -> tuple[int, ...]:
        try:
            return np.broadcast_shapes(*(a.shape[:-1] for a in arrays)) if arrays else (0,)
        except ValueError:
            raise BlackBoxError(
                f"{self._name}: argument batch shapes {[a.shape[:-1] for a in arrays]} do not broadcast"
            ) from None

    def _evaluate(
        self, arrays: Sequence[np.ndarray], shape: tuple[int, ...], describe: Callable[[int], str] | None
    ) -> np.ndarray:
        """The function on a batch of broadcast ``shape``, shape and exceptions checked, finiteness not."""
        B = math.prod(shape)
        flat = len(shape) == 1 and all(a.shape[:-1] == shape for a in arrays)
        if not flat and self._is_module:  # a user function gets the (B, d) arrays it is written for
            arrays = as_rows(arrays, shape)
        # A whole-batch failure (an exception, a wrong shape) has no one offending row: name the batch's range.
        batch = f" on the batch from {describe(0)} to {describe(B - 1)}" if describe is not None and B else ""
        try:
            with np.errstate(all="ignore"):
                out = self._fn(*arrays)
            out = np.asarray(out, dtype=float)
        except BlackBoxError:
            raise
        except Exception as exc:
            raise BlackBoxError(f"{self._name}: raised {type(exc).__name__}: {exc}{batch}") from None
        if self._is_module:
            if out.shape != (B, self._out_dim):
                raise BlackBoxError(f"{self._name}: returned shape {out.shape}, expected {(B, self._out_dim)}{batch}")
            out = out.reshape(shape + (self._out_dim,))
        elif out.shape != shape + (self._out_dim,):  # an expression that reads only some of the batch axes
            out = np.ascontiguousarray(np.broadcast_to(out, shape + (self._out_dim,)))
        return out

    def _check_finite(
        self,
        out: np.ndarray,
        shape: tuple[int, ...],
        given: Sequence[np.ndarray],
        describe: Callable[[int], str] | None,
        what: str = "returned",
    ) -> None:
        """Raise :class:`BlackBoxError` naming the first row of ``out`` that is not finite and its inputs."""
        # One read, no temporary: a sum is finite only if every term is (a finite sum can overflow, so a
        # non-finite sum is checked value by value).
        if not np.isfinite(out.sum()):
            finite = np.isfinite(out).all(axis=-1).ravel()
            if not finite.all():
                row = int(np.argmin(finite))
                at = np.unravel_index(row, shape)
                bad = out[at]
                point = ", ".join(
                    f"{k}={np.array2string(np.broadcast_to(a, shape + a.shape[-1:])[at], precision=6)}"
                    for k, a in zip(self._inputs, given)
                )
                where = f" ({describe(row)})" if describe is not None else ""
                raise BlackBoxError(f"{self._name}: {what} {bad.tolist()} (not finite) at {point}{where}")


class NoInternalVariables(BlackBox):
    """The interconnection map of a network without internal variables (a single system): ``x -> ()``.

    Stages that evaluate ``Network.interconnection_map`` get a ``(*batch, 0)`` array, as from a map with no
    outputs, and need no special case.
    """

    def __init__(self, state_dim: int) -> None:  # nothing to compile or probe: skip BlackBox.__init__
        self._name = "interconnection map (none: no internal variables)"
        self._source = ""
        self._inputs = {"x": int(state_dim)}
        self._constants = {}
        self._allowed = ()
        self._is_module = False
        self._fn = self._compile()
        self._out_dim = 0

    def _compile(self) -> Callable[..., np.ndarray]:
        def none(x: np.ndarray) -> np.ndarray:
            return np.zeros(x.shape[:-1] + (0,))

        return none
