"""The whitelist: the functions an expression may call, its operators and built-in constants, as numpy.

:data:`FUNCTIONS` maps each callable name to a :class:`Function` (its numpy implementation and accepted
arguments); the operator tables map the accepted ``ast`` operators to numpy ufuncs and name the rejected
operators and syntax for error messages. Reductions (``sum``, ``mean``, ``prod``, ``norm``, ``norm2`` and
one-argument ``max``/``min``) reduce over the component axis 0 of a vector; applied to an elementwise value
they treat it as a one-component vector (``sum``/``mean``/``prod``/``max``/``min`` return it unchanged,
``norm``/``norm2`` return ``abs``).
"""

from __future__ import annotations

import ast
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pipelines.expressions.values import Value, truth

__all__ = [
    "FUNCTIONS",
    "BUILTIN_CONSTANTS",
    "Function",
    "MAX_MIN_FOLD",
    "BINOPS",
    "REJECTED_BINOPS",
    "COMPARISONS",
    "REJECTED_COMPARISONS",
    "REJECTED_CONSTRUCTS",
    "where",
]

#: Names that are always defined.
BUILTIN_CONSTANTS: dict[str, float] = {"pi": math.pi, "e": math.e}


def _reduce_max(v: np.ndarray) -> np.ndarray:
    return np.max(v, axis=0)


def _reduce_min(v: np.ndarray) -> np.ndarray:
    return np.min(v, axis=0)


def _reduce_sum(v: np.ndarray) -> np.ndarray:
    return np.sum(v, axis=0)


def _reduce_mean(v: np.ndarray) -> np.ndarray:
    return np.mean(v, axis=0)


def _reduce_prod(v: np.ndarray) -> np.ndarray:
    return np.prod(v, axis=0)


def _reduce_norm_inf(v: np.ndarray) -> np.ndarray:
    return np.max(np.abs(v), axis=0)


def _reduce_norm2(v: np.ndarray) -> np.ndarray:
    return np.sqrt(np.sum(np.square(v), axis=0))


def _identity(v: Value) -> Value:
    return v


def _clip(a: Value, lo: Value, hi: Value) -> Value:
    return np.minimum(np.maximum(a, lo), hi)


def where(c: Value, a: Value, b: Value) -> Value:
    """``a`` where ``c`` is true (``!= 0``, NaN included), else ``b``; also ``a if c else b``."""
    return np.where(truth(c), a, b)


@dataclass(frozen=True)
class Function:
    """A whitelisted function.

    Attributes
    ----------
    min_args, max_args : int
        Accepted number of positional arguments (``max_args`` None: unbounded).
    kind : {"elementwise", "fold", "reduce"}
        ``elementwise``: ``impl(*args)`` broadcasts its arguments. ``fold``: ``impl`` is a binary ufunc
        applied left to right over 2+ arguments. ``reduce``: one argument, ``impl`` reduces axis 0 of a
        vector and ``scalar_impl`` is applied to an elementwise argument.
    """

    impl: Callable[..., Value]
    min_args: int
    max_args: int | None
    kind: str = "elementwise"
    scalar_impl: Callable[[Value], Value] = _identity

    def arity(self) -> str:
        """Human-readable accepted argument count."""
        if self.max_args is None:
            return f"{self.min_args} or more arguments"
        if self.min_args == self.max_args:
            return f"{self.min_args} argument" + ("" if self.min_args == 1 else "s")
        return f"{self.min_args} to {self.max_args} arguments"


def _unary(f: Callable[[Value], Value]) -> Function:
    return Function(f, 1, 1)


def _binary(f: Callable[[Value, Value], Value]) -> Function:
    return Function(f, 2, 2)


def _reduction(f: Callable[[np.ndarray], np.ndarray], on_elementwise: Callable[[Value], Value] = _identity) -> Function:
    return Function(f, 1, 1, "reduce", on_elementwise)


#: The whitelist of callable names. ``max``/``min`` are handled specially: one argument reduces over the
#: component axis, two or more are an elementwise ``np.maximum``/``np.minimum`` chain.
FUNCTIONS: dict[str, Function] = {
    # elementwise, one argument
    "exp": _unary(np.exp),
    "exp2": _unary(np.exp2),
    "expm1": _unary(np.expm1),
    "log": _unary(np.log),
    "log10": _unary(np.log10),
    "log2": _unary(np.log2),
    "log1p": _unary(np.log1p),
    "sqrt": _unary(np.sqrt),
    "cbrt": _unary(np.cbrt),
    "square": _unary(np.square),
    "abs": _unary(np.abs),
    "sign": _unary(np.sign),
    "floor": _unary(np.floor),
    "ceil": _unary(np.ceil),
    "sin": _unary(np.sin),
    "cos": _unary(np.cos),
    "tan": _unary(np.tan),
    "arcsin": _unary(np.arcsin),
    "asin": _unary(np.arcsin),
    "arccos": _unary(np.arccos),
    "acos": _unary(np.arccos),
    "arctan": _unary(np.arctan),
    "atan": _unary(np.arctan),
    "sinh": _unary(np.sinh),
    "cosh": _unary(np.cosh),
    "tanh": _unary(np.tanh),
    "arcsinh": _unary(np.arcsinh),
    "asinh": _unary(np.arcsinh),
    "arccosh": _unary(np.arccosh),
    "acosh": _unary(np.arccosh),
    "arctanh": _unary(np.arctanh),
    "atanh": _unary(np.arctanh),
    # elementwise, several arguments
    "arctan2": _binary(np.arctan2),
    "atan2": _binary(np.arctan2),
    "pow": _binary(np.power),
    "hypot": _binary(np.hypot),
    "minimum": Function(np.minimum, 2, None, "fold"),
    "maximum": Function(np.maximum, 2, None, "fold"),
    "clip": Function(_clip, 3, 3),
    "where": Function(where, 3, 3),
    # reductions over the component axis 0
    "sum": _reduction(_reduce_sum),
    "mean": _reduction(_reduce_mean),
    "prod": _reduction(_reduce_prod),
    "norm": _reduction(_reduce_norm_inf, np.abs),
    "norm2": _reduction(_reduce_norm2, np.abs),
    "max": Function(_reduce_max, 1, None, "reduce"),
    "min": Function(_reduce_min, 1, None, "reduce"),
}

#: ``max``/``min`` with two or more arguments: an elementwise fold.
MAX_MIN_FOLD = {"max": np.maximum, "min": np.minimum}

#: Accepted binary operators: symbol (for messages) and numpy ufunc.
BINOPS: dict[type, tuple[str, Callable[[Value, Value], Value]]] = {
    ast.Add: ("+", np.add),
    ast.Sub: ("-", np.subtract),
    ast.Mult: ("*", np.multiply),
    ast.Div: ("/", np.true_divide),
    ast.Pow: ("**", np.power),
    ast.Mod: ("%", np.mod),
    ast.FloorDiv: ("//", np.floor_divide),
}
#: Binary operators that are rejected, by symbol (for messages).
REJECTED_BINOPS: dict[type, str] = {ast.BitAnd: "&", ast.BitOr: "|", ast.BitXor: "^", ast.LShift: "<<",
                                    ast.RShift: ">>", ast.MatMult: "@"}
#: Accepted comparison operators: symbol and numpy ufunc.
COMPARISONS: dict[type, tuple[str, Callable[[Value, Value], np.ndarray]]] = {
    ast.Lt: ("<", np.less),
    ast.LtE: ("<=", np.less_equal),
    ast.Gt: (">", np.greater),
    ast.GtE: (">=", np.greater_equal),
    ast.Eq: ("==", np.equal),
    ast.NotEq: ("!=", np.not_equal),
}
#: Comparison operators that are rejected, by symbol.
REJECTED_COMPARISONS: dict[type, str] = {ast.Is: "is", ast.IsNot: "is not", ast.In: "in", ast.NotIn: "not in"}
#: Syntax that is rejected, by name (for messages).
REJECTED_CONSTRUCTS: dict[type, str] = {
    ast.Lambda: "lambda",
    ast.ListComp: "list comprehension",
    ast.SetComp: "set comprehension",
    ast.DictComp: "dict comprehension",
    ast.GeneratorExp: "generator expression",
    ast.JoinedStr: "f-string",
    ast.FormattedValue: "f-string",
    ast.Starred: "starred expression",
    ast.Dict: "dict literal",
    ast.Set: "set literal",
    ast.NamedExpr: "assignment expression ':='",
    ast.Await: "'await'",
    ast.Yield: "'yield'",
    ast.YieldFrom: "'yield from'",
    ast.Slice: "slice outside of an index",
    ast.List: "nested list literal (a list/tuple is only allowed as the whole expression)",
    ast.Tuple: "nested tuple literal (a list/tuple is only allowed as the whole expression)",
}
