"""Continuous-time subsystems: the sampled map ``x(tau)`` of ``dx/dt = f(x, u, w)`` as a black box.

A subsystem given by an ``ode`` is abstracted through its sampled map: the state after one sampling period
``tau`` with ``u`` and ``w`` held constant over it (zero-order hold), computed by ``substeps`` fixed steps of
the classical Runge-Kutta method of order 4, as SCOTS does. :class:`SampledFlow` is a
:class:`~pipelines.blackbox.BlackBox` with the same interface and checks, so that every stage that evaluates
``Subsystem.dynamics`` (the per-cell stage, the Lipschitz estimation, the audit, the closed loop) uses the
same integrator without knowing it. The guarantees hold for this integrated map, as SCOTS's do.

Integration is in bulk. A right-hand side in the scalar subset of the expression language runs with its
integrator as one compiled program over all samples (:mod:`pipelines.expressions.program`: the same operations in
the same order, no intermediate array per operation and sub-step); any other right-hand side (a vector
expression, a ``module:function``) runs :func:`rk4` here, each Runge-Kutta stage one evaluation on the whole
(broadcast) batch.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from pipelines.blackbox import BlackBox, as_rows
from pipelines.errors import SpecError
from pipelines.expressions import machine
from pipelines.expressions.program import compile_program

__all__ = ["SampledFlow", "rk4"]


def rk4(rhs: Callable[[np.ndarray], np.ndarray], x: np.ndarray, tau: float, substeps: int) -> np.ndarray:
    """``substeps`` classical Runge-Kutta 4 steps of length ``tau / substeps`` of ``dx/dt = rhs(x)``.

    Parameters
    ----------
    rhs : callable
        ``rhs(x) -> dx/dt``, same shape as ``x`` (the held inputs are bound in it).
    x : ndarray, shape (*batch, n)
        Initial states; not modified.
    tau : float
        Sampling time, > 0.
    substeps : int
        Steps per period, >= 1.

    Returns
    -------
    ndarray, shape (*batch, n)
        The approximation of ``x(tau)``: local error ``O(h^5)`` per step, ``h = tau / substeps``.
    """
    h = tau / substeps
    for _ in range(substeps):
        k1 = rhs(x)
        k2 = rhs(x + (h / 2) * k1)
        k3 = rhs(x + (h / 2) * k2)
        k4 = rhs(x + h * k3)
        # No in-place updates: a module:function may return an array it keeps (or its argument).
        x = x + (h / 6) * (k1 + 2 * (k2 + k3) + k4)
    return x


class SampledFlow(BlackBox):
    """The sampled map ``(x, u, w) -> x(tau)`` of an ODE given by its right-hand side ``f(x, u, w)``.

    Parameters
    ----------
    name, source, inputs, out_dim, constants, allowed_modules
        As for :class:`~pipelines.blackbox.BlackBox`; ``source`` is the right-hand side ``f``, ``inputs`` must
        start with the state ``x``, and ``f`` must return as many components as ``x`` has.
    sampling_time : float
        ``tau > 0``.
    substeps : int
        Runge-Kutta 4 steps per period (>= 1).

    Raises
    ------
    SpecError
        A right-hand side whose output dimension is not the state's.
    """

    def __init__(
        self,
        name: str,
        source: str,
        inputs: dict[str, int],
        out_dim: int | None = None,
        constants: dict[str, float] | None = None,
        allowed_modules: Sequence[str] | None = (),
        *,
        sampling_time: float,
        substeps: int = 5,
    ) -> None:
        if next(iter(inputs), None) != "x":
            raise ValueError(f"{name}: the first input of an ODE is its state x, got {list(inputs)}")
        if not (sampling_time > 0 and np.isfinite(sampling_time)) or int(substeps) < 1:
            raise SpecError(f"{name}: sampling_time must be > 0 and substeps >= 1, got {sampling_time}, {substeps}")
        self._tau = float(sampling_time)
        self._substeps = int(substeps)
        super().__init__(name, source, inputs, out_dim, constants, allowed_modules)
        if self.out_dim != inputs["x"]:
            raise SpecError(f"{name}: dx/dt has {self.out_dim} components, the state has {inputs['x']}")
        self._program = None if self._is_module else compile_program(
            self._source, {k: d for k, d in inputs.items() if d > 0}, self._constants, self.out_dim)

    @property
    def sampling_time(self) -> float:
        return self._tau

    @property
    def substeps(self) -> int:
        return self._substeps

    def __call__(self, *arrays: np.ndarray, describe: Callable[[int], str] | None = None) -> np.ndarray:
        """``x(tau)`` on a batch, with the checks of :meth:`BlackBox.__call__`.

        A NaN or inf anywhere in the integration reaches the result (every stage is added into the state), so
        the result's check names the initial point and its cell.
        """
        shape = self._batch_shape(arrays)
        out = self._integrate(arrays, shape, describe)
        self._check_finite(out, shape, arrays, describe, what="integrated over the sampling time to")
        return out

    def _integrate(self, arrays: Sequence[np.ndarray], shape: tuple[int, ...],
                   describe: Callable[[int], str] | None = None) -> np.ndarray:
        """``x(tau)`` on a batch of broadcast ``shape``, finiteness not checked: the compiled program where the
        right-hand side has one, else :func:`rk4` over the numpy evaluators."""
        if self._program is not None:  # the right-hand side and the integrator in one compiled pass
            B = math.prod(shape)
            rows = [np.ascontiguousarray(a, dtype=float) for a in as_rows(arrays, shape)]
            x0, u, w = (*rows, *(np.zeros((B, 0)),) * (3 - len(rows)))[:3]
            with np.errstate(all="ignore"):
                return machine.rk4(self._program, x0, u, w, self._tau, self._substeps).reshape(shape + (x0.shape[1],))
        x, held = arrays[0], arrays[1:]
        # x changes over the sub-steps: materialise it to the batch shape once. u and w are held: broadcast views
        # (an expression evaluates on them as they are), materialised once for a module:function, which gets rows.
        x0 = np.array(np.broadcast_to(x, shape + x.shape[-1:]), dtype=float)
        held = tuple(np.broadcast_to(a, shape + a.shape[-1:]) for a in held)
        if self._is_module:
            held = tuple(np.ascontiguousarray(a) for a in held)
        with np.errstate(all="ignore"):
            return rk4(lambda y: self._evaluate((y, *held), shape, describe), x0, self._tau, self._substeps)
