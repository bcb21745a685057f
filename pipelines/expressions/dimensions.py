"""What an expression's text says about the dimensions it expects, read from the parse tree (nothing evaluated).

A subsystem whose box is given by numbers (``state: {lb: -1, ub: 1, eta: 0.05}``) has as many dimensions as its
dynamics use (docs/spec.md, "Boxes and dimensions"): :func:`components_read` gives the highest component of a
variable the text indexes, :func:`output_entries` the entries of a top-level list literal.
"""

from __future__ import annotations

import ast

from pipelines.errors import ExpressionError
from pipelines.expressions.checks import check_text, parse

__all__ = ["components_read", "output_entries"]


def _non_negative_int(node: ast.AST | None) -> int | None:
    if isinstance(node, ast.Constant) and type(node.value) is int and node.value >= 0:
        return node.value
    return None


def components_read(text: str, variable: str, max_length: int = 4000) -> int:
    """The number of components of ``variable`` the text indexes: 1 + the highest ``v[k]``, or the highest stop of
    a slice ``v[a:b]``; 0 when it indexes none. Negative indices and open slices count from the end and say
    nothing about the dimension, so they are left out; a text that does not parse reads nothing here (the
    compiler names its error)."""
    try:
        tree = parse(check_text(text, max_length))
    except ExpressionError:
        return 0
    most = 0
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name) and node.value.id == variable):
            continue
        index = node.slice
        if isinstance(index, ast.Slice):
            stop = _non_negative_int(index.upper)
            start = _non_negative_int(index.lower)
            reach = stop if stop is not None else (start + 1 if start is not None else None)
        else:
            k = _non_negative_int(index)
            reach = None if k is None else k + 1
        if reach is not None:
            most = max(most, reach)
    return most


def output_entries(text: str, max_length: int = 4000) -> int:
    """The entries of a top-level list literal ``[e1, ..., en]`` (``n``), or 1 for any other text."""
    try:
        body = parse(check_text(text, max_length)).body
    except ExpressionError:
        return 1
    return len(body.elts) if isinstance(body, (ast.List, ast.Tuple)) else 1
