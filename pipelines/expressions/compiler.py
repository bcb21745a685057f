"""Safe expressions: a whitelisted subset of Python syntax compiled to vectorised numpy.

A user writes the dynamics of a subsystem (``32/(1+exp(-0.2*(x[0]+u[0]-16)))``) or an interconnection map
(``[0, sqrt(x[0]), (sqrt(x[0])+sqrt(x[1]))/2]``) as text. :func:`compile_expression` parses that text with
``ast.parse(text, mode="eval")``, checks every node against a whitelist, and builds a tree of Python closures
that call numpy ufuncs only. Nothing from the user is ever handed to ``eval``, ``exec`` or a bytecode
compiler, and no Python object other than the declared arrays, float64 scalars and whitelisted numpy
functions is reachable from an expression.

Shapes
------
Every variable ``v`` declared with dimension ``d`` is passed as an array of shape ``(d, B)`` (dimension
first, batch last). The batch may also be several axes, ``(d, *batch)``, whose shapes broadcast together by
numpy's rules (a grid of samples passed as broadcast views, without copies); ``B`` below stands for it. Inside
an expression a value is either

* *elementwise*: a scalar, or an array of shape ``(B,)`` (``x[0]``, ``mean(x)``, ``3 * u[1]``), or
* a *vector* of ``k`` components, shape ``(k, B)`` (``x``, ``x[1:3]``, ``2 * x``).

Elementwise values broadcast against vectors; two vectors must have the same number of components (or
one of them exactly one). The result of :class:`CompiledExpression` is always float64 of shape
``(out_dim, B)``: an elementwise result has ``out_dim == 1``, a vector result keeps its ``k``, and a
top-level list/tuple literal ``[e1, ..., en]`` stacks its entries (an elementwise entry is one row, a vector
entry contributes all of its rows).

Semantics a caller must know
----------------------------
* All numbers are float64; ``True``/``False`` are accepted as ``1.0``/``0.0``. A numeric literal whose
  absolute value exceeds ``1e15`` (``1e400``, ``10**400`` written out) is rejected.
* Comparisons, ``not``, ``and``, ``or`` yield float ``1.0``/``0.0`` (never Python's operand-returning
  ``and``/``or``). A value is *true* where it is ``!= 0``; NaN counts as true, as in Python.
  ``a if c else b`` is ``where(c, a, b)``: both branches are always evaluated.
* Evaluation runs under ``np.errstate(all="ignore")``: ``1/0`` is ``inf``, ``sqrt(-1)`` and ``log(-1)`` are
  NaN, ``9**9**9`` is ``inf``. Detecting non-finite results is the caller's job.
* ``//`` is ``np.floor_divide`` and ``%`` is ``np.mod`` (Python sign conventions).
* Indices and slice bounds are integer literals (optionally negative), checked against the declared
  dimension at compile time. A slice bound must lie in ``[-d, d]``; an empty slice is rejected.
* Reductions (``sum``, ``mean``, ``prod``, ``norm``, ``norm2`` and one-argument ``max``/``min``) reduce over
  the component axis 0 of a vector; applied to an elementwise value they treat it as a one-component
  vector (``sum``/``mean``/``prod``/``max``/``min`` return it unchanged, ``norm``/``norm2`` return ``abs``).
* Multi-line text follows Python's rules: a line break is only allowed inside brackets.
"""

from __future__ import annotations

import ast
import keyword
import math
import numbers
import re
import warnings
from dataclasses import dataclass
from typing import Callable, Mapping, NoReturn, Sequence, Union

import numpy as np

from pipelines.errors import ExpressionError

__all__ = ["CompiledExpression", "compile_expression", "FUNCTIONS", "MAX_NODES", "MAX_DEPTH"]

#: Largest number of AST nodes (operators and load contexts not counted) an expression may have.
MAX_NODES = 2000
#: Largest nesting depth. A left-associative chain ``a + b - c * d ...`` counts as one level, so long sums
#: are limited by :data:`MAX_NODES` only; brackets, calls, unary operators and right operands nest.
MAX_DEPTH = 60
#: Largest absolute value of a numeric literal.
MAX_LITERAL = 1e15
#: Names that are always defined.
BUILTIN_CONSTANTS: dict[str, float] = {"pi": math.pi, "e": math.e}

_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")  # same rule as spec parameter names
_ALLOWED_CONTROL = frozenset("\t\n\r")
_MAX_SHOWN = 60
#: Text that suggests a statement rather than an expression (used for a hint on syntax errors only).
_STATEMENT_HINT = re.compile(
    r";|(?<![=!<>:])=(?!=)|^\s*(import|from|def|class|del|pass|return|raise|global|for|while|with|try)\b|\n\s*\S",
    re.MULTILINE,
)

#: A value inside an evaluation: a float64 scalar, an elementwise ``(B,)`` array or a ``(k, B)`` vector.
Value = Union[float, np.floating, np.ndarray]
#: The arrays of one call, name -> float64 array of shape ``(dim, B)``.
Env = Mapping[str, np.ndarray]
Evaluator = Callable[[Env], Value]
#: The batch shape of one call: ``(B,)``, or several axes (see "Shapes").
Batch = tuple[int, ...]


# ----------------------------------------------------------------------------------------------------------
# Compiled nodes and shape rules
# ----------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Node:
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


def _truth(v: Value) -> np.ndarray:
    """Elementwise truth of ``v`` (``v != 0``; NaN is true), as a bool array of the same shape."""
    return np.not_equal(v, 0.0)


def _as_float(b: Value) -> np.ndarray:
    """Bool (or any numeric) array -> float64 array of the same shape."""
    return np.asarray(b, dtype=np.float64)


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


def _where(c: Value, a: Value, b: Value) -> Value:
    return np.where(_truth(c), a, b)


@dataclass(frozen=True)
class _Function:
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


def _unary(f: Callable[[Value], Value]) -> _Function:
    return _Function(f, 1, 1)


def _binary(f: Callable[[Value, Value], Value]) -> _Function:
    return _Function(f, 2, 2)


def _reduction(f: Callable[[np.ndarray], np.ndarray], on_elementwise: Callable[[Value], Value] = _identity) -> _Function:
    return _Function(f, 1, 1, "reduce", on_elementwise)


#: The whitelist of callable names. ``max``/``min`` are handled specially: one argument reduces over the
#: component axis, two or more are an elementwise ``np.maximum``/``np.minimum`` chain.
FUNCTIONS: dict[str, _Function] = {
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
    "minimum": _Function(np.minimum, 2, None, "fold"),
    "maximum": _Function(np.maximum, 2, None, "fold"),
    "clip": _Function(_clip, 3, 3),
    "where": _Function(_where, 3, 3),
    # reductions over the component axis 0
    "sum": _reduction(_reduce_sum),
    "mean": _reduction(_reduce_mean),
    "prod": _reduction(_reduce_prod),
    "norm": _reduction(_reduce_norm_inf, np.abs),
    "norm2": _reduction(_reduce_norm2, np.abs),
    "max": _Function(_reduce_max, 1, None, "reduce"),
    "min": _Function(_reduce_min, 1, None, "reduce"),
}

_MAX_MIN_FOLD = {"max": np.maximum, "min": np.minimum}

_BINOPS: dict[type, tuple[str, Callable[[Value, Value], Value]]] = {
    ast.Add: ("+", np.add),
    ast.Sub: ("-", np.subtract),
    ast.Mult: ("*", np.multiply),
    ast.Div: ("/", np.true_divide),
    ast.Pow: ("**", np.power),
    ast.Mod: ("%", np.mod),
    ast.FloorDiv: ("//", np.floor_divide),
}
_REJECTED_BINOPS: dict[type, str] = {
    ast.BitAnd: "&",
    ast.BitOr: "|",
    ast.BitXor: "^",
    ast.LShift: "<<",
    ast.RShift: ">>",
    ast.MatMult: "@",
}
_COMPARISONS: dict[type, tuple[str, Callable[[Value, Value], np.ndarray]]] = {
    ast.Lt: ("<", np.less),
    ast.LtE: ("<=", np.less_equal),
    ast.Gt: (">", np.greater),
    ast.GtE: (">=", np.greater_equal),
    ast.Eq: ("==", np.equal),
    ast.NotEq: ("!=", np.not_equal),
}
_REJECTED_COMPARISONS: dict[type, str] = {ast.Is: "is", ast.IsNot: "is not", ast.In: "in", ast.NotIn: "not in"}

_CONSTRUCT_NAMES: dict[type, str] = {
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

_NOT_COUNTED = (ast.expr_context, ast.operator, ast.unaryop, ast.cmpop, ast.boolop)


def _broadcast_lead(leads: Sequence[int | None]) -> int | None | str:
    """Combined leading dimension of operands, or ``"mismatch"`` if two vectors are incompatible."""
    out: int | None = None
    for lead in leads:
        if lead is None:
            continue
        if out is None or out == 1:
            out = lead
        elif lead != 1 and lead != out:
            return "mismatch"
    return out


# ----------------------------------------------------------------------------------------------------------
# Text-level checks
# ----------------------------------------------------------------------------------------------------------


def _shown(text: str) -> str:
    """The expression as quoted in messages, shortened to :data:`_MAX_SHOWN` characters."""
    if len(text) > _MAX_SHOWN:
        text = text[: _MAX_SHOWN - 3] + "..."
    return repr(text)


def _short(snippet: str, limit: int = 40) -> str:
    return snippet if len(snippet) <= limit else snippet[: limit - 3] + "..."


def _position(text: str, index: int) -> str:
    """``"column C"`` (or ``"line L, column C"`` for multi-line text) of a 0-based character index."""
    line = text.count("\n", 0, index) + 1
    col = index - (text.rfind("\n", 0, index) + 1) + 1
    return f"column {col}" if "\n" not in text else f"line {line}, column {col}"


def _check_text(text: object, max_length: int) -> str:
    """Reject non-strings, empty, over-long and non-ASCII text before parsing; return the text."""
    if not isinstance(text, str):
        raise ExpressionError(f"an expression must be a string, got {type(text).__name__}")
    if len(text) > max_length:
        raise ExpressionError(
            f"expression {_shown(text)} is {len(text)} characters, the limit is {max_length}"
        )
    if not text.strip():
        raise ExpressionError(f"expression {_shown(text)} is empty")
    for i, ch in enumerate(text):
        code = ord(ch)
        if code > 127:
            raise ExpressionError(
                f"expression {_shown(text)}: non-ASCII character {ch!r} (U+{code:04X}) at {_position(text, i)} "
                "is not allowed; expressions must be plain ASCII (look-alike letters such as Cyrillic or "
                "fullwidth ones are rejected, type the Latin letter)"
            )
        if (code < 32 or code == 127) and ch not in _ALLOWED_CONTROL:
            raise ExpressionError(
                f"expression {_shown(text)}: control character U+{code:04X} at {_position(text, i)} is not allowed"
            )
    _check_bracket_depth(text)
    return text


def _check_bracket_depth(text: str) -> None:
    """Reject brackets nested deeper than :data:`MAX_DEPTH` before the parser sees them."""
    depth = 0
    for i, ch in enumerate(text):
        if ch in "([{":
            depth += 1
            if depth > MAX_DEPTH:
                raise ExpressionError(
                    f"expression {_shown(text)}: brackets are nested more than {MAX_DEPTH} deep "
                    f"(at {_position(text, i)}); the nesting limit is {MAX_DEPTH}"
                )
        elif ch in ")]}":
            depth = max(depth - 1, 0)


def _parse(text: str) -> ast.Expression:
    """``ast.parse(text, mode="eval")`` with every parser failure turned into an :class:`ExpressionError`.

    Parser warnings (``SyntaxWarning``/``DeprecationWarning``, e.g. ``1if c else 2``) are turned into errors.
    This uses :func:`warnings.catch_warnings`, which swaps the process-wide warning filters for the duration
    of the parse (not thread-safe in Python < 3.14; harmless except for warnings raised concurrently).
    """
    stripped = text.lstrip()
    prefix = len(text) - len(stripped)
    try:
        with warnings.catch_warnings():
            # "1if c else 2" or "'\\d'" only warn in Python; reject them instead of printing user text to stderr.
            warnings.simplefilter("error", SyntaxWarning)
            warnings.simplefilter("error", DeprecationWarning)
            tree = ast.parse(stripped, mode="eval")
    except SyntaxError as exc:
        raise ExpressionError(_syntax_message(text, prefix, exc)) from None
    except (RecursionError, MemoryError):
        raise ExpressionError(
            f"expression {_shown(text)} is nested too deeply to parse; the nesting limit is {MAX_DEPTH}"
        ) from None
    except (ValueError, OverflowError, SyntaxWarning, DeprecationWarning) as exc:
        raise ExpressionError(f"expression {_shown(text)} does not parse: {exc}") from None
    if not isinstance(tree, ast.Expression):  # pragma: no cover - mode="eval" guarantees it
        raise ExpressionError(f"expression {_shown(text)} is not a single expression")
    return tree


def _syntax_message(text: str, prefix: int, exc: SyntaxError) -> str:
    """Message for a syntax error, naming where it is and the text from there on."""
    stripped = text[prefix:]
    lines = stripped.split("\n")
    lineno = exc.lineno or 1
    offset = max((exc.offset or 1) - 1, 0)
    index = prefix + sum(len(line) + 1 for line in lines[: lineno - 1]) + offset
    index = min(index, len(text))
    near = text[index:].split("\n", 1)[0].strip()
    where = _position(text, index) if index < len(text) else "the end"
    near_part = f" near {_short(near)!r}" if near else ""
    reason = exc.msg or "invalid syntax"
    hint = ""
    if "invalid syntax" in reason and _STATEMENT_HINT.search(stripped):
        hint = " (only a single expression is allowed: no statements, assignments, imports or ';')"
    return f"expression {_shown(text)}: syntax error at {where}{near_part}: {reason}{hint}"


def _check_size(text: str, tree: ast.Expression) -> None:
    """Reject trees with more than :data:`MAX_NODES` nodes or nested deeper than :data:`MAX_DEPTH`.

    The walk is iterative, so it cannot itself overflow the stack. A left operand of a binary operator
    that is again a binary operator keeps its parent's depth (``a + b + c + ...`` is one level), matching
    how the compiler evaluates such chains in a loop.
    """
    count = 0
    stack: list[tuple[ast.AST, int]] = [(tree.body, 1)]
    while stack:
        node, depth = stack.pop()
        count += 1
        if count > MAX_NODES:
            raise ExpressionError(f"expression {_shown(text)} has more than {MAX_NODES} syntax nodes, the limit")
        if depth > MAX_DEPTH:
            raise ExpressionError(
                f"expression {_shown(text)} is nested more than {MAX_DEPTH} levels deep, the limit"
            )
        for child in ast.iter_child_nodes(node):
            if isinstance(child, _NOT_COUNTED):
                continue
            same_level = isinstance(node, ast.BinOp) and child is node.left and isinstance(child, ast.BinOp)
            stack.append((child, depth if same_level else depth + 1))


# ----------------------------------------------------------------------------------------------------------
# Compiler
# ----------------------------------------------------------------------------------------------------------


class _Compiler:
    """Turns a checked ``ast.Expression`` into closures; every rejection names the construct."""

    def __init__(self, text: str, prefix: int, variables: Mapping[str, int], constants: Mapping[str, float]):
        self.text = text
        self.prefix = prefix  # characters of leading whitespace removed before parsing
        self.source = text[prefix:]
        self.variables = variables
        self.constants = constants
        self.used: set[str] = set()

    # -- messages --------------------------------------------------------------------------------------

    def fail(self, node: ast.AST | None, problem: str) -> NoReturn:
        where = ""
        if node is not None and hasattr(node, "lineno"):
            where = f" at {self._where(node)}"
        raise ExpressionError(f"expression {_shown(self.text)}: {problem.replace('{at}', where)}")

    def _where(self, node: ast.AST) -> str:
        lines = self.source.split("\n")
        line, col = getattr(node, "lineno", 1), getattr(node, "col_offset", 0)
        index = self.prefix + sum(len(s) + 1 for s in lines[: line - 1]) + col
        return _position(self.text, min(index, max(len(self.text) - 1, 0)))

    def segment(self, node: ast.AST) -> str:
        """The source text of ``node``, shortened for messages."""
        try:
            seg = ast.get_source_segment(self.source, node)
        except Exception:  # pragma: no cover - defensive: positions are always present after parsing
            seg = None
        if seg is None:
            try:
                seg = ast.unparse(node)
            except Exception:  # pragma: no cover
                seg = type(node).__name__
        return _short(" ".join(seg.split()))

    def allowed_summary(self) -> str:
        names = ", ".join(self.allowed_names())
        return (
            f"allowed: numbers, names {names}, indexing like v[0], v[-1], v[1:3], operators + - * / ** % //, "
            "comparisons < <= > >= == !=, and/or/not, 'a if c else b', and calls of whitelisted functions "
            "by bare name"
        )

    def allowed_names(self) -> list[str]:
        return [*self.variables, *self.constants, *BUILTIN_CONSTANTS]

    # -- dispatch --------------------------------------------------------------------------------------

    def top(self, tree: ast.Expression) -> tuple[Callable[[Env, int], np.ndarray], int]:
        """Compile the whole expression; return ``(assemble(env, B) -> (out_dim, B) array, out_dim)``."""
        body = tree.body
        if isinstance(body, (ast.List, ast.Tuple)):
            return self.output_list(body)
        node = self.expr(body)
        return _assemble_single(node), node.lead or 1

    def output_list(self, node: ast.List | ast.Tuple) -> tuple[Callable[[Env, int], np.ndarray], int]:
        if not node.elts:
            self.fail(node, "an empty list{at} has no output components; write at least one entry")
        entries = [self.expr(elt) for elt in node.elts]
        return _assemble_list(entries), sum(e.lead or 1 for e in entries)

    def expr(self, node: ast.AST) -> _Node:
        method = _DISPATCH.get(type(node))
        if method is None:
            self.reject_construct(node)
        return method(self, node)

    def reject_construct(self, node: ast.AST) -> NoReturn:
        name = _CONSTRUCT_NAMES.get(type(node), f"{type(node).__name__} syntax")
        self.fail(node, f"{name} {self.segment(node)!r}{{at}} is not allowed ({self.allowed_summary()})")

    # -- leaves ----------------------------------------------------------------------------------------

    def constant(self, node: ast.Constant) -> _Node:
        value = node.value
        if isinstance(value, bool):
            return _constant_node(1.0 if value else 0.0)
        if isinstance(value, int):
            if abs(value) > MAX_LITERAL:
                self.fail(node, f"numeric literal {self.segment(node)!r}{{at}} is too large (|value| > {MAX_LITERAL:g})")
            return _constant_node(float(value))
        if isinstance(value, float):
            if not math.isfinite(value) or abs(value) > MAX_LITERAL:
                self.fail(node, f"numeric literal {self.segment(node)!r}{{at}} is too large (|value| > {MAX_LITERAL:g})")
            return _constant_node(value)
        kind = {
            complex: "complex literal",
            str: "string literal",
            bytes: "bytes literal",
            type(None): "'None'",
            type(Ellipsis): "ellipsis '...'",
        }.get(type(value), f"{type(value).__name__} literal")
        self.fail(node, f"{kind} {self.segment(node)!r}{{at}} is not allowed; only real numbers are")

    def name(self, node: ast.Name) -> _Node:
        ident = node.id
        if ident in self.variables:
            self.used.add(ident)
            return _Node(_variable_getter(ident), self.variables[ident])
        if ident in self.constants:
            return _constant_node(self.constants[ident])
        if ident in BUILTIN_CONSTANTS:
            return _constant_node(BUILTIN_CONSTANTS[ident])
        if ident in FUNCTIONS:
            self.fail(node, f"function {ident!r}{{at}} must be called, e.g. {ident}(...)")
        self.fail(
            node,
            f"unknown name {_short(ident)!r}{{at}} (allowed names: {', '.join(self.allowed_names())})",
        )

    def attribute(self, node: ast.Attribute) -> NoReturn:
        self.fail(
            node,
            f"attribute access '.{_short(node.attr)}' in {self.segment(node)!r}{{at}} is not allowed "
            f"(attributes are never accessible; call functions by bare name, e.g. exp(x[0]); "
            f"{self.allowed_summary()})",
        )

    # -- indexing --------------------------------------------------------------------------------------

    def subscript(self, node: ast.Subscript) -> _Node:
        target = node.value
        if not isinstance(target, ast.Name):
            if isinstance(target, ast.Attribute):
                self.attribute(target)
            self.fail(
                node,
                f"subscript {self.segment(node)!r}{{at}} is not allowed: only a variable name can be indexed "
                f"(variables: {', '.join(self.variables) or 'none'})",
            )
        ident = target.id
        if ident not in self.variables:
            if ident in self.constants or ident in BUILTIN_CONSTANTS:
                self.fail(node, f"{ident!r} is a scalar constant and cannot be indexed ({self.segment(node)!r}{{at}})")
            self.name(target)  # raises: unknown name or uncalled function
        dim = self.variables[ident]
        self.used.add(ident)
        index = node.slice
        if isinstance(index, ast.Slice):
            return self.slice(node, ident, dim, index)
        i = self.int_literal(index, ident, "index")
        if not -dim <= i < dim:
            self.fail(
                node,
                f"index {i} in {self.segment(node)!r}{{at}} is out of range for {ident!r} of dimension {dim} "
                f"(valid indices: {-dim}..{dim - 1})",
            )
        return _Node(_index_getter(ident, i), None)

    def slice(self, node: ast.Subscript, ident: str, dim: int, s: ast.Slice) -> _Node:
        bounds = []
        for part, what in ((s.lower, "slice start"), (s.upper, "slice stop"), (s.step, "slice step")):
            if part is None:
                bounds.append(None)
                continue
            value = self.int_literal(part, ident, what)
            if what != "slice step" and not -dim <= value <= dim:
                self.fail(
                    node,
                    f"{what} {value} in {self.segment(node)!r}{{at}} is out of range for {ident!r} of dimension "
                    f"{dim} (valid bounds: {-dim}..{dim})",
                )
            if what == "slice step" and value == 0:
                self.fail(node, f"slice step 0 in {self.segment(node)!r}{{at}} is not allowed")
            bounds.append(value)
        sl = slice(*bounds)
        count = len(range(dim)[sl])
        if count == 0:
            self.fail(node, f"slice {self.segment(node)!r}{{at}} selects no components of {ident!r} (dimension {dim})")
        return _Node(_slice_getter(ident, sl), count)

    def int_literal(self, node: ast.AST, ident: str, what: str) -> int:
        """The value of an integer literal ``5`` or ``-5`` used as an index or slice bound."""
        negate = False
        inner = node
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            negate = isinstance(node.op, ast.USub)
            inner = node.operand
        if isinstance(inner, ast.Constant) and type(inner.value) is int and abs(inner.value) <= MAX_LITERAL:
            return -inner.value if negate else inner.value
        self.fail(
            node,
            f"{what} {self.segment(node)!r} of {ident!r}{{at}} must be an integer literal such as 0, -1 or 2",
        )

    # -- operators -------------------------------------------------------------------------------------

    def binop(self, node: ast.BinOp) -> _Node:
        """Compile a left-associative chain ``((a op b) op c) ...`` into one loop (no deep recursion)."""
        spine: list[ast.BinOp] = []
        cur: ast.AST = node
        while isinstance(cur, ast.BinOp):
            spine.append(cur)
            cur = cur.left
        first = self.expr(cur)
        lead = first.lead
        steps: list[tuple[Callable[[Value, Value], Value], Evaluator]] = []
        for b in reversed(spine):
            symbol, ufunc = self.binop_ufunc(b)
            right = self.expr(b.right)
            combined = _broadcast_lead([lead, right.lead])
            if combined == "mismatch":
                self.fail(
                    b,
                    f"operands of {symbol!r} in {self.segment(b)!r}{{at}} have incompatible dimensions "
                    f"{lead} and {right.lead}",
                )
            lead = combined
            steps.append((ufunc, right.fn))
        return _Node(_fold_steps(first.fn, tuple(steps)), lead)

    def binop_ufunc(self, node: ast.BinOp) -> tuple[str, Callable[[Value, Value], Value]]:
        op = type(node.op)
        if op in _BINOPS:
            return _BINOPS[op]
        symbol = _REJECTED_BINOPS.get(op, op.__name__)
        if op is ast.MatMult:
            hint = "matrix multiplication is not supported; write the sum of products explicitly"
        else:
            hint = "bitwise operators are not supported; for logic use 'and', 'or', 'not'"
        self.fail(node, f"operator {symbol!r} in {self.segment(node)!r}{{at}} is not allowed ({hint})")

    def unaryop(self, node: ast.UnaryOp) -> _Node:
        operand = self.expr(node.operand)
        if isinstance(node.op, ast.USub):
            return _Node(_apply1(np.negative, operand.fn), operand.lead)
        if isinstance(node.op, ast.UAdd):
            return operand
        if isinstance(node.op, ast.Not):
            return _Node(_apply1(_logical_not, operand.fn), operand.lead)
        self.fail(
            node,
            f"operator '~' in {self.segment(node)!r}{{at}} is not allowed (bitwise operators are not supported; "
            "for logic use 'not')",
        )

    def compare(self, node: ast.Compare) -> _Node:
        operands = [self.expr(node.left)] + [self.expr(c) for c in node.comparators]
        ufuncs = []
        for op in node.ops:
            if type(op) not in _COMPARISONS:
                symbol = _REJECTED_COMPARISONS.get(type(op), type(op).__name__)
                self.fail(
                    node,
                    f"comparison {symbol!r} in {self.segment(node)!r}{{at}} is not allowed "
                    "(allowed: < <= > >= == !=)",
                )
            ufuncs.append(_COMPARISONS[type(op)][1])
        lead = self.combine_leads(node, operands, "comparison")
        fns = tuple(o.fn for o in operands)
        return _Node(_chained_comparison(tuple(ufuncs), fns), lead)

    def boolop(self, node: ast.BoolOp) -> _Node:
        values = [self.expr(v) for v in node.values]
        lead = self.combine_leads(node, values, "'and'" if isinstance(node.op, ast.And) else "'or'")
        ufunc = np.logical_and if isinstance(node.op, ast.And) else np.logical_or
        return _Node(_logical_chain(ufunc, tuple(v.fn for v in values)), lead)

    def ifexp(self, node: ast.IfExp) -> _Node:
        test, body, orelse = self.expr(node.test), self.expr(node.body), self.expr(node.orelse)
        lead = self.combine_leads(node, [test, body, orelse], "conditional expression")
        return _Node(_apply3(_where, test.fn, body.fn, orelse.fn), lead)

    def combine_leads(self, node: ast.AST, parts: Sequence[_Node], what: str) -> int | None:
        lead = _broadcast_lead([p.lead for p in parts])
        if lead == "mismatch":
            dims = ", ".join("elementwise" if p.lead is None else str(p.lead) for p in parts)
            self.fail(node, f"operands of {what} {self.segment(node)!r}{{at}} have incompatible dimensions ({dims})")
        return lead

    # -- calls -----------------------------------------------------------------------------------------

    def call(self, node: ast.Call) -> _Node:
        func = node.func
        if isinstance(func, ast.Attribute):
            self.attribute(func)
        if not isinstance(func, ast.Name):
            self.fail(
                node,
                f"call of {self.segment(func)!r}{{at}} is not allowed: only whitelisted functions can be called, "
                f"by bare name (functions: {', '.join(FUNCTIONS)})",
            )
        fname = func.id
        spec = FUNCTIONS.get(fname)
        if spec is None:
            self.fail(
                node,
                f"function {_short(fname)!r}{{at}} is not allowed (allowed functions: {', '.join(FUNCTIONS)})",
            )
        if node.keywords:
            kw = node.keywords[0]
            label = f"'{kw.arg}='" if kw.arg is not None else "'**'"
            self.fail(
                node,
                f"keyword argument {label} in call of {fname!r}{{at}} is not allowed; pass arguments by position",
            )
        for arg in node.args:
            if isinstance(arg, ast.Starred):
                self.fail(arg, f"starred argument {self.segment(arg)!r} in call of {fname!r}{{at}} is not allowed")
        n = len(node.args)
        if n < spec.min_args or (spec.max_args is not None and n > spec.max_args):
            self.fail(node, f"function {fname!r}{{at}} takes {spec.arity()}, got {n}")
        args = [self.expr(a) for a in node.args]
        return self.apply_function(node, fname, spec, args)

    def apply_function(self, node: ast.Call, fname: str, spec: _Function, args: list[_Node]) -> _Node:
        if fname in _MAX_MIN_FOLD and len(args) >= 2:
            lead = self.combine_leads(node, args, f"{fname}()")
            return _Node(_fold_args(_MAX_MIN_FOLD[fname], tuple(a.fn for a in args)), lead)
        if spec.kind == "reduce":
            (arg,) = args
            if arg.lead is None:
                return _Node(_apply1(spec.scalar_impl, arg.fn), None)
            return _Node(_apply1(spec.impl, arg.fn), None)
        lead = self.combine_leads(node, args, f"{fname}()")
        fns = tuple(a.fn for a in args)
        if spec.kind == "fold":
            return _Node(_fold_args(spec.impl, fns), lead)
        if len(fns) == 1:
            return _Node(_apply1(spec.impl, fns[0]), lead)
        if len(fns) == 2:
            return _Node(_apply2(spec.impl, fns[0], fns[1]), lead)
        return _Node(_apply3(spec.impl, *fns), lead)


_DISPATCH: dict[type, Callable[[_Compiler, ast.AST], _Node]] = {
    ast.Constant: _Compiler.constant,
    ast.Name: _Compiler.name,
    ast.Attribute: _Compiler.attribute,
    ast.Subscript: _Compiler.subscript,
    ast.BinOp: _Compiler.binop,
    ast.UnaryOp: _Compiler.unaryop,
    ast.Compare: _Compiler.compare,
    ast.BoolOp: _Compiler.boolop,
    ast.IfExp: _Compiler.ifexp,
    ast.Call: _Compiler.call,
}


# ----------------------------------------------------------------------------------------------------------
# Closure builders (kept outside the compiler so closures hold no reference to AST or compiler state)
# ----------------------------------------------------------------------------------------------------------


def _constant_node(value: float) -> _Node:
    v = np.float64(value)
    return _Node(lambda env: v, None)


def _variable_getter(ident: str) -> Evaluator:
    return lambda env: env[ident]


def _index_getter(ident: str, i: int) -> Evaluator:
    return lambda env: env[ident][i]


def _slice_getter(ident: str, sl: slice) -> Evaluator:
    return lambda env: env[ident][sl]


def _apply1(f: Callable[[Value], Value], a: Evaluator) -> Evaluator:
    return lambda env: f(a(env))


def _apply2(f: Callable[[Value, Value], Value], a: Evaluator, b: Evaluator) -> Evaluator:
    return lambda env: f(a(env), b(env))


def _apply3(f: Callable[[Value, Value, Value], Value], a: Evaluator, b: Evaluator, c: Evaluator) -> Evaluator:
    return lambda env: f(a(env), b(env), c(env))


def _logical_not(v: Value) -> np.ndarray:
    return _as_float(np.equal(v, 0.0))


def _fold_steps(first: Evaluator, steps: tuple[tuple[Callable[[Value, Value], Value], Evaluator], ...]) -> Evaluator:
    """``first op1 r1 op2 r2 ...`` evaluated left to right in a loop."""

    def run(env: Env) -> Value:
        value = first(env)
        for ufunc, right in steps:
            value = ufunc(value, right(env))
        return value

    return run


def _fold_args(ufunc: Callable[[Value, Value], Value], fns: tuple[Evaluator, ...]) -> Evaluator:
    """``ufunc(ufunc(a, b), c) ...`` over 2+ arguments."""

    def run(env: Env) -> Value:
        value = fns[0](env)
        for f in fns[1:]:
            value = ufunc(value, f(env))
        return value

    return run


def _chained_comparison(ufuncs: tuple[Callable[[Value, Value], np.ndarray], ...], fns: tuple[Evaluator, ...]) -> Evaluator:
    """``a < b <= c`` as ``(a < b) and (b <= c)``, every operand evaluated once, result float 1.0/0.0."""

    def run(env: Env) -> Value:
        values = [f(env) for f in fns]
        result = ufuncs[0](values[0], values[1])
        for k in range(1, len(ufuncs)):
            result = np.logical_and(result, ufuncs[k](values[k], values[k + 1]))
        return _as_float(result)

    return run


def _logical_chain(ufunc: Callable[[Value, Value], np.ndarray], fns: tuple[Evaluator, ...]) -> Evaluator:
    """Elementwise ``and``/``or`` over truth values (``!= 0``), result float 1.0/0.0."""

    def run(env: Env) -> Value:
        result = _truth(fns[0](env))
        for f in fns[1:]:
            result = ufunc(result, _truth(f(env)))
        return _as_float(result)

    return run


def _assemble_single(node: _Node) -> Callable[[Env, Batch], np.ndarray]:
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


def _assemble_list(entries: list[_Node]) -> Callable[[Env, Batch], np.ndarray]:
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


# ----------------------------------------------------------------------------------------------------------
# Public API
# ----------------------------------------------------------------------------------------------------------


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
        assemble: Callable[[Env, int], np.ndarray],
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

    def _prepare(self, arrays: Mapping[str, object]) -> tuple[dict[str, np.ndarray], Batch]:
        unknown = [k for k in arrays if k not in self._variables]
        if unknown:
            raise ExpressionError(
                f"expression {_shown(self._text)}: unknown variable {unknown[0]!r} passed "
                f"(declared: {', '.join(self._variables)})"
            )
        missing = sorted(self._used - set(arrays))
        if missing:
            raise ExpressionError(f"expression {_shown(self._text)}: variable {missing[0]!r} was not passed")
        if not arrays:
            raise ExpressionError(
                f"expression {_shown(self._text)}: pass at least one variable array so the batch size is known"
            )
        env: dict[str, np.ndarray] = {}
        batch: Batch | None = None
        for name, raw in arrays.items():
            arr = _as_batch_array(self._text, name, raw, self._variables[name])
            shape = arr.shape[1:]
            if batch is not None and shape != batch:
                if len(shape) == 1 and len(batch) == 1:
                    raise ExpressionError(
                        f"expression {_shown(self._text)}: variable {name!r} has batch size {shape[0]}, "
                        f"others have {batch[0]}"
                    )
                try:
                    shape = np.broadcast_shapes(batch, shape)
                except ValueError:
                    raise ExpressionError(
                        f"expression {_shown(self._text)}: variable {name!r} has batch shape {arr.shape[1:]}, "
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


def _as_batch_array(text: str, name: str, raw: object, dim: int) -> np.ndarray:
    """``raw`` as a float64 array of shape ``(dim, B)`` or ``(dim, *batch)``, or :class:`ExpressionError`."""
    try:
        if np.iscomplexobj(raw):
            raise TypeError("complex values are not allowed")
        arr = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ExpressionError(f"expression {_shown(text)}: variable {name!r} is not a real float array ({exc})") from None
    if arr.ndim < 2 or arr.shape[0] != dim:
        raise ExpressionError(
            f"expression {_shown(text)}: variable {name!r} must have shape ({dim}, B), got {arr.shape}"
        )
    return arr


def _check_name(kind: str, name: object) -> str:
    if (
        not isinstance(name, str)
        or not _IDENTIFIER.match(name)
        or name.startswith("__")
        or keyword.iskeyword(name)
    ):
        raise ExpressionError(
            f"{kind} name {name!r} is not allowed: names are ASCII letters, digits and '_', do not start with a "
            "digit or '__', and are not Python keywords"
        )
    if name in FUNCTIONS:
        raise ExpressionError(f"{kind} name {name!r} clashes with the function {name}()")
    if name in BUILTIN_CONSTANTS:
        raise ExpressionError(f"{kind} name {name!r} clashes with the built-in constant {name}")
    return name


def _check_declarations(
    variables: Mapping[str, int], constants: Mapping[str, float] | None
) -> tuple[dict[str, int], dict[str, float]]:
    """Validate variable dimensions and constant values; return clean copies."""
    if not isinstance(variables, Mapping):
        raise ExpressionError(f"variables must be a mapping name -> dimension, got {type(variables).__name__}")
    clean_vars: dict[str, int] = {}
    for name, dim in variables.items():
        _check_name("variable", name)
        if isinstance(dim, bool) or not isinstance(dim, numbers.Integral) or dim < 1:
            raise ExpressionError(f"variable {name!r} must have a positive integer dimension, got {dim!r}")
        clean_vars[name] = int(dim)
    clean_consts: dict[str, float] = {}
    if constants is not None:
        if not isinstance(constants, Mapping):
            raise ExpressionError(f"constants must be a mapping name -> number, got {type(constants).__name__}")
        for name, value in constants.items():
            _check_name("constant", name)
            if name in clean_vars:
                raise ExpressionError(f"constant {name!r} has the same name as a variable")
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(float(value)):
                raise ExpressionError(f"constant {name!r} must be a finite real number, got {value!r}")
            clean_consts[name] = float(value)
    return clean_vars, clean_consts


def compile_expression(
    text: str,
    variables: dict[str, int],
    constants: dict[str, float] | None = None,
    max_length: int = 4000,
) -> CompiledExpression:
    """Compile a safe expression to a vectorised numpy function.

    Parameters
    ----------
    text : str
        The expression, e.g. ``"32/(1+exp(-0.2*(x[0]+u[0]-16)))"`` or ``"[0, sqrt(x[0])]"``.
    variables : dict of str to int
        Variable name -> dimension ``d``; at call time the variable is an array of shape ``(d, B)``.
    constants : dict of str to float, optional
        Extra named scalars, substituted as float64 (e.g. ``{"tau": 0.5}``).
    max_length : int
        Longest accepted ``text``, in characters.

    Returns
    -------
    CompiledExpression
        Callable as ``expr(**arrays) -> ndarray of shape (expr.output_dim(), B)``.

    Raises
    ------
    ExpressionError
        For anything outside the whitelist (the message names the construct and where it is), for unknown
        names, out-of-range indices, incompatible vector dimensions, over-long or over-nested text, and for
        invalid ``variables``/``constants``.
    """
    if isinstance(max_length, bool) or not isinstance(max_length, int) or max_length < 1:
        raise ExpressionError(f"max_length must be a positive integer, got {max_length!r}")
    clean_vars, clean_consts = _check_declarations(variables, constants)
    text = _check_text(text, max_length)
    tree = _parse(text)
    _check_size(text, tree)
    compiler = _Compiler(text, len(text) - len(text.lstrip()), clean_vars, clean_consts)
    try:
        assemble, out_dim = compiler.top(tree)
    except RecursionError:  # pragma: no cover - depth is bounded by _check_size
        raise ExpressionError(f"expression {_shown(text)} is nested too deeply") from None
    return CompiledExpression(text, clean_vars, frozenset(compiler.used), assemble, out_dim)
