"""The stack machine that runs :class:`~.program.Program` s (numba): an ODE's right-hand side and its Runge-Kutta
integration in one pass over the samples, in blocks of :data:`~.program.BLOCK` rows whose intermediate values stay
in cache, each opcode's loop over a block one vectorisable loop. It executes opcodes :mod:`.program` emitted,
never text; :func:`rk4` takes the steps of :func:`pipelines.integrators.rk4` in its order.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from pipelines.expressions.program import (
    ADD,
    ATAN2,
    BLOCK,
    CONST,
    DIV,
    EQ,
    GE,
    GT,
    LE,
    LT,
    MAXIMUM,
    MINIMUM,
    MUL,
    NEG,
    POW,
    RDIV_C,
    REG,
    RSUB_C,
    SELECT,
    SUB,
    WITH_CONSTANT,
    Program,
    U,
    W,
    X,
)

__all__ = ["rk4"]


@njit(cache=True, nogil=True, error_model="numpy")
def _maximum(a: float, b: float) -> float:
    if a != a:
        return a
    if b != b:
        return b
    return a if a >= b else b


@njit(cache=True, nogil=True, error_model="numpy")
def _minimum(a: float, b: float) -> float:
    if a != a:
        return a
    if b != b:
        return b
    return a if a <= b else b


@njit(cache=True, nogil=True, error_model="numpy")
def _sign(a: float) -> float:
    if a > 0:
        return 1.0
    if a < 0:
        return -1.0
    return a  # 0 and NaN


@njit(cache=True, nogil=True, error_model="numpy")
def _unary(op: int, v: float) -> float:  # noqa: PLR0911 - one branch per opcode
    if op == 50:
        return math.exp(v)
    if op == 51:
        return math.log(v) if v > 0 else (-math.inf if v == 0 else math.nan)
    if op == 52:
        return math.sqrt(v) if v >= 0 else math.nan
    if op == 53:
        return math.sin(v)
    if op == 54:
        return math.cos(v)
    if op == 55:
        return math.tan(v)
    if op == 56:
        return math.tanh(v)
    if op == 57:
        return abs(v)
    if op == 58:
        return math.atan(v)
    if op == 59:
        return math.sinh(v)
    if op == 60:
        return math.cosh(v)
    if op == 61:
        return v * v
    if op == 62:
        return math.expm1(v)
    if op == 63:
        return math.log1p(v) if v >= -1 else math.nan
    if op == 64:
        return math.log10(v) if v > 0 else (-math.inf if v == 0 else math.nan)
    if op == 65:
        return math.log2(v) if v > 0 else (-math.inf if v == 0 else math.nan)
    if op == 66:
        return 2.0 ** v
    if op == 67:
        return math.asin(v) if -1 <= v <= 1 else math.nan
    if op == 68:
        return math.acos(v) if -1 <= v <= 1 else math.nan
    if op == 69:
        return np.floor(v)
    if op == 70:
        return np.ceil(v)
    return _sign(v)


@njit(cache=True, nogil=True, error_model="numpy")
def _binary(op: int, a: float, b: float) -> float:
    if op == MINIMUM:
        return _minimum(a, b)
    if op == MAXIMUM:
        return _maximum(a, b)
    if op == ATAN2:
        return math.atan2(a, b)
    return math.hypot(a, b)


@njit(cache=True, nogil=True, error_model="numpy")
def _operator(op, a, b, m):  # noqa: PLR0912 - one branch per opcode
    """``a[:m] = a OP b`` for a binary operator or comparison (comparisons give 1.0 or 0.0)."""
    if op == ADD:
        for i in range(m):
            a[i] = a[i] + b[i]
    elif op == SUB:
        for i in range(m):
            a[i] = a[i] - b[i]
    elif op == MUL:
        for i in range(m):
            a[i] = a[i] * b[i]
    elif op == DIV:
        for i in range(m):
            a[i] = a[i] / b[i]
    elif op == POW:
        for i in range(m):
            a[i] = a[i] ** b[i]
    elif op == LT:
        for i in range(m):
            a[i] = 1.0 if a[i] < b[i] else 0.0
    elif op == LE:
        for i in range(m):
            a[i] = 1.0 if a[i] <= b[i] else 0.0
    elif op == GT:
        for i in range(m):
            a[i] = 1.0 if a[i] > b[i] else 0.0
    elif op == GE:
        for i in range(m):
            a[i] = 1.0 if a[i] >= b[i] else 0.0
    elif op == EQ:
        for i in range(m):
            a[i] = 1.0 if a[i] == b[i] else 0.0
    else:
        for i in range(m):
            a[i] = 1.0 if a[i] != b[i] else 0.0


@njit(cache=True, nogil=True, error_model="numpy")
def _with_constant(op, a, c, m):  # noqa: PLR0912 - one branch per opcode
    """``a[:m] = a OP c`` for an operator with a constant right operand (:data:`WITH_CONSTANT`)."""
    if op == ADD + WITH_CONSTANT:
        for i in range(m):
            a[i] = a[i] + c
    elif op == SUB + WITH_CONSTANT:
        for i in range(m):
            a[i] = a[i] - c
    elif op == MUL + WITH_CONSTANT:
        for i in range(m):
            a[i] = a[i] * c
    elif op == DIV + WITH_CONSTANT:
        for i in range(m):
            a[i] = a[i] / c
    elif op == POW + WITH_CONSTANT:
        for i in range(m):
            a[i] = a[i] ** c
    elif op == RSUB_C:
        for i in range(m):
            a[i] = c - a[i]
    elif op == RDIV_C:
        for i in range(m):
            a[i] = c / a[i]
    elif op == LT + WITH_CONSTANT:
        for i in range(m):
            a[i] = 1.0 if a[i] < c else 0.0
    elif op == LE + WITH_CONSTANT:
        for i in range(m):
            a[i] = 1.0 if a[i] <= c else 0.0
    elif op == GT + WITH_CONSTANT:
        for i in range(m):
            a[i] = 1.0 if a[i] > c else 0.0
    elif op == GE + WITH_CONSTANT:
        for i in range(m):
            a[i] = 1.0 if a[i] >= c else 0.0
    elif op == EQ + WITH_CONSTANT:
        for i in range(m):
            a[i] = 1.0 if a[i] == c else 0.0
    else:
        for i in range(m):
            a[i] = 1.0 if a[i] != c else 0.0


@njit(cache=True, nogil=True, error_model="numpy")
def _component(ops, first, last, consts, xs, us, ws, regs, m, stack):  # noqa: PLR0912 - one branch per opcode
    """Run rows ``first:last`` of ``ops`` on the first ``m`` columns of ``xs``, ``us``, ``ws`` and the registers
    ``regs`` (component-major: one contiguous row per component); the value is ``stack[0, :m]``."""
    sp = 0
    for r in range(first, last):
        op, arg = ops[r, 0], ops[r, 1]
        if op == CONST:
            v = consts[arg]
            for i in range(m):
                stack[sp, i] = v
            sp += 1
        elif op == X:
            for i in range(m):
                stack[sp, i] = xs[arg, i]
            sp += 1
        elif op == U:
            for i in range(m):
                stack[sp, i] = us[arg, i]
            sp += 1
        elif op == W:
            for i in range(m):
                stack[sp, i] = ws[arg, i]
            sp += 1
        elif op == REG:
            for i in range(m):
                stack[sp, i] = regs[arg, i]
            sp += 1
        elif op == NEG:
            for i in range(m):
                stack[sp - 1, i] = -stack[sp - 1, i]
        elif op == SELECT:
            sp -= 2
            for i in range(m):
                if stack[sp - 1, i] != 0:  # NaN is true, as numpy's truth
                    stack[sp - 1, i] = stack[sp, i]
                else:
                    stack[sp - 1, i] = stack[sp + 1, i]
        elif op < SELECT:  # a binary operator or comparison
            sp -= 1
            _operator(op, stack[sp - 1], stack[sp], m)
        elif op >= WITH_CONSTANT:
            _with_constant(op, stack[sp - 1], consts[arg], m)
        elif op < 50:
            sp -= 1
            for i in range(m):
                stack[sp - 1, i] = _binary(op, stack[sp - 1, i], stack[sp, i])
        else:
            for i in range(m):
                stack[sp - 1, i] = _unary(op, stack[sp - 1, i])


@njit(cache=True, nogil=True, error_model="numpy")
def _rhs(ops, starts, consts, first, xs, us, ws, regs, m, stack, out):
    """The right-hand side at ``xs``: registers ``first ..`` (those that read the state), then the components."""
    n_regs = regs.shape[0]
    for k in range(first, n_regs):
        _component(ops, starts[k], starts[k + 1], consts, xs, us, ws, regs, m, stack)
        for i in range(m):
            regs[k, i] = stack[0, i]
    for c in range(starts.size - 1 - n_regs):
        _component(ops, starts[n_regs + c], starts[n_regs + c + 1], consts, xs, us, ws, regs, m, stack)
        for i in range(m):
            out[c, i] = stack[0, i]


@njit(cache=True, nogil=True, error_model="numpy")
def _rk4(ops, starts, consts, depth, n_regs, held, x0, U, W, h, substeps):
    B, n = x0.shape
    out = np.empty((B, n))
    stack = np.empty((depth, BLOCK))
    regs = np.empty((n_regs, BLOCK))
    # Component-major blocks: every loop below and in _component runs over contiguous rows.
    us = np.empty((U.shape[1], BLOCK))
    ws = np.empty((W.shape[1], BLOCK))
    x = np.empty((n, BLOCK))
    y = np.empty((n, BLOCK))
    k1 = np.empty((n, BLOCK))
    k2 = np.empty((n, BLOCK))
    k3 = np.empty((n, BLOCK))
    k4 = np.empty((n, BLOCK))
    half, sixth = h / 2, h / 6
    for lo in range(0, B, BLOCK):
        m = min(BLOCK, B - lo)
        for i in range(m):
            for d in range(n):
                x[d, i] = x0[lo + i, d]
            for d in range(us.shape[0]):
                us[d, i] = U[lo + i, d]
            for d in range(ws.shape[0]):
                ws[d, i] = W[lo + i, d]
        for k in range(held):  # the registers that read no state: once, held through every stage and sub-step
            _component(ops, starts[k], starts[k + 1], consts, x, us, ws, regs, m, stack)
            for i in range(m):
                regs[k, i] = stack[0, i]
        for _ in range(substeps):  # the steps of pipelines.integrators.rk4, in its order
            _rhs(ops, starts, consts, held, x, us, ws, regs, m, stack, k1)
            for d in range(n):
                for i in range(m):
                    y[d, i] = x[d, i] + half * k1[d, i]
            _rhs(ops, starts, consts, held, y, us, ws, regs, m, stack, k2)
            for d in range(n):
                for i in range(m):
                    y[d, i] = x[d, i] + half * k2[d, i]
            _rhs(ops, starts, consts, held, y, us, ws, regs, m, stack, k3)
            for d in range(n):
                for i in range(m):
                    y[d, i] = x[d, i] + h * k3[d, i]
            _rhs(ops, starts, consts, held, y, us, ws, regs, m, stack, k4)
            for d in range(n):
                for i in range(m):
                    x[d, i] = x[d, i] + sixth * (k1[d, i] + 2 * (k2[d, i] + k3[d, i]) + k4[d, i])
        for i in range(m):
            for d in range(n):
                out[lo + i, d] = x[d, i]
    return out


def rk4(program: Program, x0: np.ndarray, u: np.ndarray, w: np.ndarray, tau: float, substeps: int) -> np.ndarray:
    """``substeps`` Runge-Kutta 4 steps of ``dx/dt = program(x, u, w)`` over ``tau``, for rows of ``x0`` (B, n),
    ``u`` (B, m) and ``w`` (B, p) (contiguous float64): what :func:`pipelines.integrators.rk4` computes with the
    numpy evaluators, in one compiled pass."""
    return _rk4(program.ops, program.starts, program.constants, program.depth, program.registers, program.held,
                x0, u, w, tau / substeps, int(substeps))
