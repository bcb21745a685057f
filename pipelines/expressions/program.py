"""Scalar expressions as programs of a compiled stack machine: the right-hand side of an ODE and its Runge-Kutta
integration in one pass over the samples, without an intermediate array per operation and sub-step.

:func:`compile_program` turns the text of a safe expression that :func:`~.compiler.compile_expression` has
accepted into a :class:`Program`: per output component a postfix sequence of opcodes over numbered constants and
the components ``x[i]``, ``u[j]``, ``w[k]``. Only a scalar subset of the language has opcodes (numbers and named
constants, indexed variables, ``+ - * / **``, unary ``-``, comparisons as conditions of ``a if c else b`` and
``where``, the one- and two-argument elementwise functions below, ``clip``, ``min``/``max`` of several
arguments); for anything else (vector values, slices, reductions) it returns ``None`` and the caller keeps the
numpy evaluators. The machine (:func:`.machine.rk4`) is one numba function compiled once for every program: it executes
opcodes this module emitted, never text, so nothing from a spec is compiled or executed beyond the whitelist.

The operations are those of the numpy evaluators, in the order of the parse tree, with numpy's error model (a
division by zero is ``inf``, not an exception), and :func:`.machine.rk4` takes the steps of
:func:`pipelines.integrators.rk4` in its order: ``+ - * /``, comparisons and selections give the same bits, powers
and transcendental functions agree to within a few ulps (numpy's SIMD implementations and the C library's
differ). Every stage evaluates an ODE through one of the two paths, so the map the guarantees are about is one map. Samples are processed in blocks of :data:`BLOCK` rows
whose intermediate values stay in cache, and each opcode's loop over a block is one vectorisable loop.
"""

from __future__ import annotations

import ast
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipelines.expressions.checks import parse
from pipelines.expressions.functions import BINOPS, BUILTIN_CONSTANTS, FUNCTIONS

__all__ = ["Program", "compile_program"]

#: Rows of a block: the stack of a deep expression (32 levels) stays within 64 KiB.
BLOCK = 256

# Opcodes (the second column of a program row is the operand: a constant's or a component's index).
CONST, X, U, W, REG = 0, 1, 2, 3, 4
ADD, SUB, MUL, DIV, POW, NEG = 10, 11, 12, 13, 14, 15
LT, LE, GT, GE, EQ, NE = 20, 21, 22, 23, 24, 25
SELECT = 30
MINIMUM, MAXIMUM, ATAN2, HYPOT = 40, 41, 42, 43
#: A binary operator or comparison whose right operand is the constant named by the operand: ``op + WITH_CONSTANT``
#: (``c - a`` and ``c / a`` as :data:`RSUB_C`, :data:`RDIV_C`); a pass per sample fewer than pushing the constant.
WITH_CONSTANT = 100
RSUB_C, RDIV_C = 116, 117
#: ``c OP a`` as ``a OP' c``: exact for these (IEEE addition and multiplication commute; comparisons mirror).
_SWAPPED = {ADD: ADD, MUL: MUL, SUB: RSUB_C - WITH_CONSTANT, DIV: RDIV_C - WITH_CONSTANT,
            LT: GT, LE: GE, GT: LT, GE: LE, EQ: EQ, NE: NE}
UNARY = {"exp": 50, "log": 51, "sqrt": 52, "sin": 53, "cos": 54, "tan": 55, "tanh": 56, "abs": 57,
         "arctan": 58, "atan": 58, "sinh": 59, "cosh": 60, "square": 61, "expm1": 62, "log1p": 63, "log10": 64,
         "log2": 65, "exp2": 66, "arcsin": 67, "asin": 67, "arccos": 68, "acos": 68, "floor": 69, "ceil": 70,
         "sign": 71}
BINARY = {"minimum": MINIMUM, "maximum": MAXIMUM, "arctan2": ATAN2, "atan2": ATAN2, "hypot": HYPOT, "pow": POW}
_BINOPS = {ast.Add: ADD, ast.Sub: SUB, ast.Mult: MUL, ast.Div: DIV, ast.Pow: POW}
_COMPARE = {ast.Lt: LT, ast.LtE: LE, ast.Gt: GT, ast.GtE: GE, ast.Eq: EQ, ast.NotEq: NE}
_VARIABLES = {"x": X, "u": U, "w": W}


@dataclass(frozen=True)
class Program:
    """Postfix programs (module docstring): first the registers' definitions, then one per output component.

    A register holds a sub-expression that the components would otherwise compute more than once, or one that
    reads only ``u``, ``w`` and constants: those (the first :attr:`held` registers) are computed once per sample
    and held through every Runge-Kutta stage and sub-step, as the inputs are; the others once per evaluation of
    the right-hand side. A register's definition reads only registers defined before it.

    Attributes
    ----------
    ops : ndarray of int64, shape (K, 2)
        ``(opcode, operand)`` rows, the programs one after the other.
    starts : ndarray of int64, shape (registers + n_out + 1,)
        Program ``k``'s rows are ``ops[starts[k]:starts[k + 1]]``: registers ``0 .. registers - 1``, then the
        components.
    constants : ndarray of float64
    depth : int
        The deepest stack any program needs.
    registers : int
    held : int
        Registers ``0 .. held - 1`` read no state.
    """

    ops: np.ndarray
    starts: np.ndarray
    constants: np.ndarray
    depth: int
    registers: int = 0
    held: int = 0

    @property
    def out_dim(self) -> int:
        return int(self.starts.size - 1 - self.registers)


class _Unsupported(Exception):
    """A construct without an opcode: the numpy evaluators run the expression instead."""


class _Emitter:
    """Postfix code of scalar expressions. ``registers`` (the text of a sub-expression, as :func:`ast.dump` writes
    it -> its register) are read instead of computed; every other composite sub-expression met is counted in
    :attr:`visits`: how often, and how often where its parent reads the state (or it is a whole component)."""

    def __init__(self, variables: dict[str, int], constants: dict[str, float],
                 registers: dict[str, int] | None = None) -> None:
        self.variables = variables
        self.names = {**BUILTIN_CONSTANTS, **constants}
        self.ops: list[tuple[int, int]] = []
        self.constants: list[float] = []
        self.depth = 0
        self.sp = 0
        self.registers = registers or {}
        self.visits: dict[str, _Visits] = {}
        self._state_context = True

    def _visit(self, node: ast.AST) -> bool:
        """Count a composite sub-expression, or push its register: whether it was pushed."""
        key = ast.dump(node)
        if key in self.registers:
            self.push(REG, self.registers[key])
            return True
        v = self.visits.get(key)
        if v is None:
            v = self.visits[key] = _Visits(node)
        v.count += 1
        v.in_state_context += self._state_context
        self._state_context = v.reads_state
        return False

    def value(self, node: ast.AST) -> None:
        """A register's definition: the code of ``node`` itself (not its register), as a condition where it is a
        comparison."""
        self._state_context = _reads_state(node)
        if isinstance(node, ast.Compare):
            self._compare(node)
        else:
            self._emit(node)

    def push(self, op: int, arg: int = 0, pops: int = 0) -> None:
        self.ops.append((op, arg))
        self.sp += 1 - pops
        self.depth = max(self.depth, self.sp)

    def constant(self, value: float) -> None:
        self.constants.append(float(value))
        self.push(CONST, len(self.constants) - 1)

    def fold(self, node: ast.AST) -> np.float64 | None:
        """The value of a sub-expression without variables, computed as the numpy evaluators compute it (numpy
        float64 operations, numpy's error model), or ``None``: so a constant sub-expression is one constant
        opcode, not a computation per sample, and gives the same bits."""
        if isinstance(node, ast.Constant) and isinstance(node.value, int | float) and not isinstance(node.value, bool):
            return np.float64(node.value)
        if isinstance(node, ast.Name) and node.id in self.names:
            return np.float64(self.names[node.id])
        parts: list[ast.expr]
        impl: Callable[..., Any]
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
            parts, impl = [node.operand], (np.negative if isinstance(node.op, ast.USub) else np.positive)
        elif isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            parts, impl = [node.left, node.right], BINOPS[type(node.op)][1]
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and not node.keywords
              and (node.func.id in UNARY and len(node.args) == 1 or node.func.id in BINARY and len(node.args) == 2)):
            parts, impl = list(node.args), FUNCTIONS[node.func.id].impl
        else:
            return None
        values = [self.fold(p) for p in parts]
        if any(v is None for v in values):
            return None
        with np.errstate(all="ignore"):
            return np.float64(impl(*values))  # type: ignore[arg-type]

    def emit(self, node: ast.AST) -> None:
        """Postfix code of a scalar sub-expression, or :class:`_Unsupported`."""
        value = self.fold(node)
        if value is not None:
            self.constant(float(value))
            return
        if isinstance(node, ast.Compare):  # a comparison is a condition only (as the numpy evaluators read it)
            raise _Unsupported("comparison as a value")
        outer = self._state_context
        if _composite(node) and self._visit(node):
            return
        try:
            self._emit(node)
        finally:
            self._state_context = outer

    def _emit(self, node: ast.AST) -> None:
        if isinstance(node, ast.Constant) and isinstance(node.value, int | float) and not isinstance(node.value, bool):
            self.constant(float(node.value))
        elif isinstance(node, ast.Name) and node.id in self.names:
            self.constant(self.names[node.id])
        elif isinstance(node, ast.Name) and node.id in _VARIABLES and self.variables.get(node.id) == 1:
            self.push(_VARIABLES[node.id], 0)  # a variable of one component is its component
        elif (isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name) and node.value.id in _VARIABLES
              and node.value.id in self.variables and isinstance(node.slice, ast.Constant)
              and type(node.slice.value) is int and 0 <= node.slice.value < self.variables[node.value.id]):
            self.push(_VARIABLES[node.value.id], node.slice.value)
        elif isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            self.emit(node.left)
            self.emit(node.right)
            self.push(_BINOPS[type(node.op)], pops=2)
        elif isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
            self.emit(node.operand)
            if isinstance(node.op, ast.USub):
                self.push(NEG, pops=1)
        elif isinstance(node, ast.IfExp):
            self.condition(node.test)
            self.emit(node.body)
            self.emit(node.orelse)
            self.push(SELECT, pops=3)
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and not node.keywords:
            self.call(node.func.id, node.args)
        else:
            raise _Unsupported(type(node).__name__)

    def condition(self, node: ast.AST) -> None:
        """A condition: one comparison (a boolean, as numpy's), or a value that is true where it is not 0."""
        if isinstance(node, ast.Compare):
            outer = self._state_context
            if self._visit(node):
                return
            try:
                self._compare(node)
            finally:
                self._state_context = outer
        else:
            self.emit(node)

    def _compare(self, node: ast.Compare) -> None:
        if len(node.ops) != 1 or type(node.ops[0]) not in _COMPARE:
            raise _Unsupported("chained comparison")
        self.emit(node.left)
        self.emit(node.comparators[0])
        self.push(_COMPARE[type(node.ops[0])], pops=2)

    def call(self, name: str, args: list[ast.expr]) -> None:
        if name in UNARY and len(args) == 1:
            self.emit(args[0])
            self.push(UNARY[name], pops=1)
        elif name in BINARY and len(args) == 2:
            self.emit(args[0])
            self.emit(args[1])
            self.push(BINARY[name], pops=2)
        elif name in ("minimum", "maximum", "min", "max") and len(args) >= 2:  # a fold, left to right
            op = MINIMUM if name in ("minimum", "min") else MAXIMUM
            self.emit(args[0])
            for a in args[1:]:
                self.emit(a)
                self.push(op, pops=2)
        elif name == "clip" and len(args) == 3:  # minimum(maximum(a, lo), hi), as the numpy clip
            self.emit(args[0])
            self.emit(args[1])
            self.push(MAXIMUM, pops=2)
            self.emit(args[2])
            self.push(MINIMUM, pops=2)
        elif name == "where" and len(args) == 3:
            self.condition(args[0])
            self.emit(args[1])
            self.emit(args[2])
            self.push(SELECT, pops=3)
        else:
            raise _Unsupported(name)


#: Most registers a program gets (each is a row of a block of the machine's memory).
MAX_REGISTERS = 64


@dataclass
class _Visits:
    node: ast.AST
    count: int = 0
    in_state_context: int = 0

    def __post_init__(self) -> None:
        self.reads_state = _reads_state(self.node)
        self.size = sum(1 for _ in ast.walk(self.node))


def _reads_state(node: ast.AST) -> bool:
    return any(isinstance(n, ast.Name) and n.id == "x" for n in ast.walk(node))


def _composite(node: ast.AST) -> bool:
    """Whether a sub-expression computes something (a register can save work), not a leaf."""
    return isinstance(node, ast.BinOp | ast.IfExp | ast.Call | ast.Compare) or (
        isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub))


def _registers(components: list[ast.expr], variables: dict[str, int], constants: dict[str, float]
               ) -> list[_Visits]:
    """The sub-expressions to keep in registers, in the order they are defined: those met more than once, and
    the largest that read no state inside one that does (so they are held over the integration), chosen largest
    first; the held ones first, then by size (a definition reads only smaller ones)."""
    chosen: dict[str, _Visits] = {}
    while len(chosen) < MAX_REGISTERS:
        em = _Emitter(variables, constants, {k: i for i, k in enumerate(chosen)})
        for c in components:
            em.emit(c)
        for v in chosen.values():
            em.value(v.node)
        candidates = [v for v in em.visits.values()
                      if v.count >= 2 or (not v.reads_state and v.in_state_context)]
        if not candidates:
            break
        best = max(candidates, key=lambda v: v.size)
        chosen[ast.dump(best.node)] = best
    return sorted(chosen.values(), key=lambda v: (v.reads_state, v.size))


def compile_program(text: str, variables: dict[str, int], constants: dict[str, float] | None = None,
                    out_dim: int | None = None) -> Program | None:
    """The :class:`Program` of an expression that :func:`~.compiler.compile_expression` accepted (its checks are
    not repeated here), or ``None`` where a construct has no opcode.

    ``out_dim``: the components expected (a list of that many scalars, or one scalar for 1).
    """
    body = parse(text).body
    components = body.elts if isinstance(body, ast.List) else [body]
    if out_dim is not None and len(components) != out_dim:
        return None
    constants = dict(constants or {})
    try:
        registers = _registers(components, variables, constants)
        em = _Emitter(variables, constants, {ast.dump(v.node): i for i, v in enumerate(registers)})
        ops: list[tuple[int, int]] = []
        starts = [0]
        for r in registers:
            em.sp, em.ops = 0, []
            em.value(r.node)
            ops += _with_constants(em.ops)
            starts.append(len(ops))
        for c in components:
            em.sp, em.ops = 0, []
            em.emit(c)
            ops += _with_constants(em.ops)
            starts.append(len(ops))
    except _Unsupported:
        return None
    return Program(np.asarray(ops, dtype=np.int64).reshape(-1, 2), np.asarray(starts, dtype=np.int64),
                   np.asarray(em.constants, dtype=np.float64), max(1, em.depth), len(registers),
                   sum(not r.reads_state for r in registers))


def _with_constants(ops: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """``CONST k; OP`` as ``OP_C k``, and ``CONST k; LOAD; OP`` as ``LOAD; OP'_C k`` (:data:`WITH_CONSTANT`)."""
    out: list[tuple[int, int]] = []
    for op, arg in ops:
        if op in _SWAPPED and out and out[-1][0] == CONST:
            out[-1] = (op + WITH_CONSTANT, out[-1][1])
        elif (op in _SWAPPED and len(out) >= 2 and out[-2][0] == CONST and out[-1][0] in (X, U, W, REG)):
            k = out[-2][1]
            out[-2:] = [out[-1], (_SWAPPED[op] + WITH_CONSTANT, k)]
        else:
            out.append((op, arg))
    return out
