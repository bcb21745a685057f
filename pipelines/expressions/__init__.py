"""Safe expressions: a whitelisted subset of Python syntax compiled to vectorised numpy.

A user writes the dynamics of a subsystem (``32/(1+exp(-0.2*(x[0]+u[0]-16)))``) or an interconnection map
(``[0, sqrt(x[0]), (sqrt(x[0])+sqrt(x[1]))/2]``) as text. :func:`compile_expression` parses that text with
``ast.parse(text, mode="eval")``, checks every node against a whitelist, and builds a tree of Python closures
that call numpy ufuncs only. Nothing from the user is ever handed to ``eval``, ``exec`` or a bytecode
compiler, and no Python object other than the declared arrays, float64 scalars and whitelisted numpy
functions is reachable from an expression.

Modules
-------
:mod:`~pipelines.expressions.values`
    Values inside an evaluation (elementwise or vector), the compiled-node type and the shape rule.
:mod:`~pipelines.expressions.functions`
    The whitelist: :data:`FUNCTIONS`, the operators and the built-in constants, as numpy.
:mod:`~pipelines.expressions.checks`
    Checks before compilation: text, size and depth limits (:data:`MAX_NODES`, :data:`MAX_DEPTH`), parsing,
    declared names; the helpers that quote text in error messages.
:mod:`~pipelines.expressions.evaluators`
    Evaluator combinators: the closures a compiled expression is made of.
:mod:`~pipelines.expressions.compiler`
    The AST -> closures compiler and :func:`compile_expression`.
:mod:`~pipelines.expressions.compiled`
    :class:`CompiledExpression`, the callable result.
:mod:`~pipelines.expressions.dimensions`
    The dimensions a text implies (the highest ``x[k]`` it reads, its output list), from the parse tree.

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

from pipelines.expressions.checks import MAX_DEPTH, MAX_LITERAL, MAX_NODES
from pipelines.expressions.compiled import CompiledExpression
from pipelines.expressions.compiler import compile_expression
from pipelines.expressions.functions import BUILTIN_CONSTANTS, FUNCTIONS

__all__ = [
    "CompiledExpression",
    "compile_expression",
    "FUNCTIONS",
    "BUILTIN_CONSTANTS",
    "MAX_NODES",
    "MAX_DEPTH",
    "MAX_LITERAL",
]
