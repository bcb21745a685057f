"""Evaluator combinators: the closures a compiled expression is made of.

Each builder returns a closure ``fn(env) -> value`` (see :mod:`pipelines.expressions.values`) that calls numpy
ufuncs only. They are kept outside the compiler so that closures hold no reference to the AST or to compiler
state. Left-associative chains and folds run in a loop, not by recursion, so long sums cost no stack depth.
:func:`assemble_single` and :func:`assemble_list` build the final ``(out_dim, *batch)`` float64 array.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from pipelines.expressions.values import Assembler, Batch, Env, Evaluator, Node, Value, as_float, truth

__all__ = [
    "constant_node",
    "variable_getter",
    "index_getter",
    "slice_getter",
    "apply1",
    "apply2",
    "apply3",
    "logical_not",
    "fold_steps",
    "fold_args",
    "chained_comparison",
    "logical_chain",
    "assemble_single",
    "assemble_list",
]


def constant_node(value: float) -> Node:
    v = np.float64(value)
    return Node(lambda env: v, None)


def variable_getter(ident: str) -> Evaluator:
    return lambda env: env[ident]


def index_getter(ident: str, i: int) -> Evaluator:
    return lambda env: env[ident][i]


def slice_getter(ident: str, sl: slice) -> Evaluator:
    return lambda env: env[ident][sl]


def apply1(f: Callable[[Value], Value], a: Evaluator) -> Evaluator:
    return lambda env: f(a(env))


def apply2(f: Callable[[Value, Value], Value], a: Evaluator, b: Evaluator) -> Evaluator:
    return lambda env: f(a(env), b(env))


def apply3(f: Callable[[Value, Value, Value], Value], a: Evaluator, b: Evaluator, c: Evaluator) -> Evaluator:
    return lambda env: f(a(env), b(env), c(env))


def logical_not(v: Value) -> np.ndarray:
    return as_float(np.equal(v, 0.0))


def fold_steps(first: Evaluator, steps: tuple[tuple[Callable[[Value, Value], Value], Evaluator], ...]) -> Evaluator:
    """``first op1 r1 op2 r2 ...`` evaluated left to right in a loop."""

    def run(env: Env) -> Value:
        value = first(env)
        for ufunc, right in steps:
            value = ufunc(value, right(env))
        return value

    return run


def fold_args(ufunc: Callable[[Value, Value], Value], fns: tuple[Evaluator, ...]) -> Evaluator:
    """``ufunc(ufunc(a, b), c) ...`` over 2+ arguments."""

    def run(env: Env) -> Value:
        value = fns[0](env)
        for f in fns[1:]:
            value = ufunc(value, f(env))
        return value

    return run


def chained_comparison(ufuncs: tuple[Callable[[Value, Value], np.ndarray], ...], fns: tuple[Evaluator, ...]) -> Evaluator:
    """``a < b <= c`` as ``(a < b) and (b <= c)``, every operand evaluated once, result float 1.0/0.0."""

    def run(env: Env) -> Value:
        values = [f(env) for f in fns]
        result = ufuncs[0](values[0], values[1])
        for k in range(1, len(ufuncs)):
            result = np.logical_and(result, ufuncs[k](values[k], values[k + 1]))
        return as_float(result)

    return run


def logical_chain(ufunc: Callable[[Value, Value], np.ndarray], fns: tuple[Evaluator, ...]) -> Evaluator:
    """Elementwise ``and``/``or`` over truth values (``!= 0``), result float 1.0/0.0."""

    def run(env: Env) -> Value:
        result = truth(fns[0](env))
        for f in fns[1:]:
            result = ufunc(result, truth(f(env)))
        return as_float(result)

    return run


def assemble_single(node: Node) -> Assembler:
    """Output of a non-list expression: ``(1, B)`` for an elementwise value, ``(k, B)`` for a vector."""
    rows = node.lead or 1
    fn = node.fn

    def run(env: Env, batch: Batch) -> np.ndarray:
        value = np.asarray(fn(env), dtype=np.float64)
        if node.lead is None:
            if value.shape == batch and value.flags.owndata and value.flags.c_contiguous:
                # A ufunc's fresh result (inputs reach an elementwise value only as views): no copy needed.
                return value[np.newaxis]
            value = np.broadcast_to(value, batch)[np.newaxis]
        # Row-major whatever the inputs' strides (a ufunc lays its output out like its inputs), so that
        # reductions over the leading batch axes read contiguous rows.
        return np.array(np.broadcast_to(value, (rows,) + batch), dtype=np.float64, order="C")

    return run


def assemble_list(entries: list[Node]) -> Assembler:
    """Output of ``[e1, ..., en]``: elementwise entries are one row each, vector entries all their rows."""
    layout = tuple((e.fn, e.lead) for e in entries)
    total = sum(lead or 1 for _, lead in layout)

    def run(env: Env, batch: Batch) -> np.ndarray:
        out = np.empty((total,) + batch, dtype=np.float64)
        row = 0
        for fn, lead in layout:
            value = fn(env)
            if lead is None:
                out[row] = np.broadcast_to(value, batch)
                row += 1
            else:
                out[row : row + lead] = np.broadcast_to(value, (lead,) + batch)
                row += lead
        return out

    return run
