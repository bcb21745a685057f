"""Checks before compilation: the text, its size and nesting, the parse, the declared names.

Everything a user can write wrong before the compiler sees a tree is rejected here with a message that quotes
the expression (shortened by :func:`shown`) and names the position (:func:`position`): non-ASCII or control
characters, over-long text, brackets nested too deeply (checked before the parser, which would otherwise
recurse), syntax errors, trees over :data:`MAX_NODES` nodes or :data:`MAX_DEPTH` levels, and variable or
constant names that are not identifiers or clash with a function or built-in constant.

Parsing is serialised by one lock (:data:`PARSE_LOCK`, :func:`parse_python`): CPython 3.11's ``ast.parse`` is not
safe in two threads at once (gh-106905: ``SystemError: AST constructor recursion depth mismatch``, seen as a 500
among 20 concurrent ``POST /jobs``), and :func:`warnings.catch_warnings` swaps process-wide state. Every parse of
user text in the package goes through :func:`parse_python`.
"""

from __future__ import annotations

import ast
import keyword
import math
import numbers
import re
import threading
import warnings
from collections.abc import Mapping

from pipelines.errors import ExpressionError
from pipelines.expressions.functions import BUILTIN_CONSTANTS, FUNCTIONS

__all__ = [
    "MAX_NODES",
    "MAX_DEPTH",
    "MAX_LITERAL",
    "shown",
    "short",
    "position",
    "check_text",
    "parse",
    "parse_python",
    "PARSE_LOCK",
    "check_size",
    "check_declarations",
]

#: Largest number of AST nodes (operators and load contexts not counted) an expression may have.
MAX_NODES = 2000
#: Largest nesting depth. A left-associative chain ``a + b - c * d ...`` counts as one level, so long sums
#: are limited by :data:`MAX_NODES` only; brackets, calls, unary operators and right operands nest.
MAX_DEPTH = 60
#: Largest absolute value of a numeric literal.
MAX_LITERAL = 1e15

#: Held by every ``ast.parse`` of the package (:func:`parse_python`): one parse at a time in a process.
PARSE_LOCK = threading.Lock()

_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")  # same rule as spec parameter names
_ALLOWED_CONTROL = frozenset("\t\n\r")
_MAX_SHOWN = 60
#: Text that suggests a statement rather than an expression (used for a hint on syntax errors only).
_STATEMENT_HINT = re.compile(
    r";|(?<![=!<>:])=(?!=)|^\s*(import|from|def|class|del|pass|return|raise|global|for|while|with|try)\b|\n\s*\S",
    re.MULTILINE,
)

_NOT_COUNTED = (ast.expr_context, ast.operator, ast.unaryop, ast.cmpop, ast.boolop)


def shown(text: str) -> str:
    """The expression as quoted in messages, shortened to :data:`_MAX_SHOWN` characters."""
    if len(text) > _MAX_SHOWN:
        text = text[: _MAX_SHOWN - 3] + "..."
    return repr(text)


def short(snippet: str, limit: int = 40) -> str:
    """A snippet of the expression, shortened to ``limit`` characters."""
    return snippet if len(snippet) <= limit else snippet[: limit - 3] + "..."


def position(text: str, index: int) -> str:
    """``"column C"`` (or ``"line L, column C"`` for multi-line text) of a 0-based character index."""
    line = text.count("\n", 0, index) + 1
    col = index - (text.rfind("\n", 0, index) + 1) + 1
    return f"column {col}" if "\n" not in text else f"line {line}, column {col}"


def check_text(text: object, max_length: int) -> str:
    """Reject non-strings, empty, over-long and non-ASCII text before parsing; return the text."""
    if not isinstance(text, str):
        raise ExpressionError(f"an expression must be a string, got {type(text).__name__}")
    if len(text) > max_length:
        raise ExpressionError(
            f"expression {shown(text)} is {len(text)} characters, the limit is {max_length}"
        )
    if not text.strip():
        raise ExpressionError(f"expression {shown(text)} is empty")
    for i, ch in enumerate(text):
        code = ord(ch)
        if code > 127:
            raise ExpressionError(
                f"expression {shown(text)}: non-ASCII character {ch!r} (U+{code:04X}) at {position(text, i)} "
                "is not allowed; expressions must be plain ASCII (look-alike letters such as Cyrillic or "
                "fullwidth ones are rejected, type the Latin letter)"
            )
        if (code < 32 or code == 127) and ch not in _ALLOWED_CONTROL:
            raise ExpressionError(
                f"expression {shown(text)}: control character U+{code:04X} at {position(text, i)} is not allowed"
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
                    f"expression {shown(text)}: brackets are nested more than {MAX_DEPTH} deep "
                    f"(at {position(text, i)}); the nesting limit is {MAX_DEPTH}"
                )
        elif ch in ")]}":
            depth = max(depth - 1, 0)


def parse_python(text: str, mode: str = "eval") -> ast.AST:
    """``ast.parse(text, mode=mode)`` under :data:`PARSE_LOCK`, with ``SyntaxWarning`` and ``DeprecationWarning``
    raised as errors (``1if c else 2``, ``'\\d'`` only warn in Python; a user's text is never printed to stderr).
    Raises what ``ast.parse`` raises."""
    with PARSE_LOCK, warnings.catch_warnings():
        warnings.simplefilter("error", SyntaxWarning)
        warnings.simplefilter("error", DeprecationWarning)
        return ast.parse(text, mode=mode)


def parse(text: str) -> ast.Expression:
    """``ast.parse(text, mode="eval")`` with every parser failure turned into an :class:`ExpressionError`.

    Parser warnings (``SyntaxWarning``/``DeprecationWarning``, e.g. ``1if c else 2``) are turned into errors. One
    parse at a time (:func:`parse_python`).
    """
    stripped = text.lstrip()
    prefix = len(text) - len(stripped)
    try:
        tree = parse_python(stripped)
    except SyntaxError as exc:
        raise ExpressionError(_syntax_message(text, prefix, exc)) from None
    except (RecursionError, MemoryError):
        raise ExpressionError(
            f"expression {shown(text)} is nested too deeply to parse; the nesting limit is {MAX_DEPTH}"
        ) from None
    except (ValueError, OverflowError, SyntaxWarning, DeprecationWarning) as exc:
        raise ExpressionError(f"expression {shown(text)} does not parse: {exc}") from None
    if not isinstance(tree, ast.Expression):  # pragma: no cover - mode="eval" guarantees it
        raise ExpressionError(f"expression {shown(text)} is not a single expression")
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
    where = position(text, index) if index < len(text) else "the end"
    near_part = f" near {short(near)!r}" if near else ""
    reason = exc.msg or "invalid syntax"
    hint = ""
    if "invalid syntax" in reason and _STATEMENT_HINT.search(stripped):
        hint = " (only a single expression is allowed: no statements, assignments, imports or ';')"
    return f"expression {shown(text)}: syntax error at {where}{near_part}: {reason}{hint}"


def check_size(text: str, tree: ast.Expression) -> None:
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
            raise ExpressionError(f"expression {shown(text)} has more than {MAX_NODES} syntax nodes, the limit")
        if depth > MAX_DEPTH:
            raise ExpressionError(
                f"expression {shown(text)} is nested more than {MAX_DEPTH} levels deep, the limit"
            )
        for child in ast.iter_child_nodes(node):
            if isinstance(child, _NOT_COUNTED):
                continue
            same_level = isinstance(node, ast.BinOp) and child is node.left and isinstance(child, ast.BinOp)
            stack.append((child, depth if same_level else depth + 1))


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


def check_declarations(
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
