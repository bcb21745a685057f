"""The compiler: a checked parse tree -> a tree of evaluator closures (:func:`compile_expression`).

:func:`compile_expression` checks the declarations and the text (:mod:`pipelines.expressions.checks`), parses
it, and hands the tree to :class:`_Compiler`, which dispatches on the node type, rejects everything outside the
whitelist (:mod:`pipelines.expressions.functions`) with a message naming the construct and where it is, infers
each sub-expression's shape statically (:mod:`pipelines.expressions.values`) and builds the closures
(:mod:`pipelines.expressions.evaluators`). Nothing from the user is ever handed to ``eval``, ``exec`` or a
bytecode compiler.
"""

from __future__ import annotations

import ast
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NoReturn

import numpy as np

from pipelines.errors import ExpressionError
from pipelines.expressions.checks import (
    MAX_LITERAL,
    check_declarations,
    check_size,
    check_text,
    parse,
    position,
    short,
    shown,
)
from pipelines.expressions.compiled import CompiledExpression
from pipelines.expressions.evaluators import (
    apply1,
    apply2,
    apply3,
    assemble_list,
    assemble_single,
    chained_comparison,
    constant_node,
    fold_args,
    fold_steps,
    index_getter,
    logical_chain,
    logical_not,
    slice_getter,
    variable_getter,
)
from pipelines.expressions.functions import (
    BINOPS,
    BUILTIN_CONSTANTS,
    COMPARISONS,
    FUNCTIONS,
    MAX_MIN_FOLD,
    REJECTED_BINOPS,
    REJECTED_COMPARISONS,
    REJECTED_CONSTRUCTS,
    Function,
    where,
)
from pipelines.expressions.values import Assembler, Evaluator, Node, Value, broadcast_lead

__all__ = ["compile_expression"]


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
        raise ExpressionError(f"expression {shown(self.text)}: {problem.replace('{at}', where)}")

    def _where(self, node: ast.AST) -> str:
        lines = self.source.split("\n")
        line, col = getattr(node, "lineno", 1), getattr(node, "col_offset", 0)
        index = self.prefix + sum(len(s) + 1 for s in lines[: line - 1]) + col
        return position(self.text, min(index, max(len(self.text) - 1, 0)))

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
        return short(" ".join(seg.split()))

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

    def top(self, tree: ast.Expression) -> tuple[Assembler, int]:
        """Compile the whole expression; return ``(assemble(env, B) -> (out_dim, B) array, out_dim)``."""
        body = tree.body
        if isinstance(body, (ast.List, ast.Tuple)):
            return self.output_list(body)
        node = self.expr(body)
        return assemble_single(node), node.lead or 1

    def output_list(self, node: ast.List | ast.Tuple) -> tuple[Assembler, int]:
        if not node.elts:
            self.fail(node, "an empty list{at} has no output components; write at least one entry")
        entries = [self.expr(elt) for elt in node.elts]
        return assemble_list(entries), sum(e.lead or 1 for e in entries)

    def expr(self, node: ast.AST) -> Node:
        method = _DISPATCH.get(type(node))
        if method is None:
            self.reject_construct(node)
        return method(self, node)

    def reject_construct(self, node: ast.AST) -> NoReturn:
        name = REJECTED_CONSTRUCTS.get(type(node), f"{type(node).__name__} syntax")
        self.fail(node, f"{name} {self.segment(node)!r}{{at}} is not allowed ({self.allowed_summary()})")

    # -- leaves ----------------------------------------------------------------------------------------

    def constant(self, node: ast.Constant) -> Node:
        value = node.value
        if isinstance(value, bool):
            return constant_node(1.0 if value else 0.0)
        if isinstance(value, int):
            if abs(value) > MAX_LITERAL:
                self.fail(node, f"numeric literal {self.segment(node)!r}{{at}} is too large (|value| > {MAX_LITERAL:g})")
            return constant_node(float(value))
        if isinstance(value, float):
            if not math.isfinite(value) or abs(value) > MAX_LITERAL:
                self.fail(node, f"numeric literal {self.segment(node)!r}{{at}} is too large (|value| > {MAX_LITERAL:g})")
            return constant_node(value)
        kind = {
            complex: "complex literal",
            str: "string literal",
            bytes: "bytes literal",
            type(None): "'None'",
            type(Ellipsis): "ellipsis '...'",
        }.get(type(value), f"{type(value).__name__} literal")
        self.fail(node, f"{kind} {self.segment(node)!r}{{at}} is not allowed; only real numbers are")

    def name(self, node: ast.Name) -> Node:
        ident = node.id
        if ident in self.variables:
            self.used.add(ident)
            return Node(variable_getter(ident), self.variables[ident])
        if ident in self.constants:
            return constant_node(self.constants[ident])
        if ident in BUILTIN_CONSTANTS:
            return constant_node(BUILTIN_CONSTANTS[ident])
        if ident in FUNCTIONS:
            self.fail(node, f"function {ident!r}{{at}} must be called, e.g. {ident}(...)")
        self.fail(
            node,
            f"unknown name {short(ident)!r}{{at}} (allowed names: {', '.join(self.allowed_names())})",
        )

    def attribute(self, node: ast.Attribute) -> NoReturn:
        self.fail(
            node,
            f"attribute access '.{short(node.attr)}' in {self.segment(node)!r}{{at}} is not allowed "
            f"(attributes are never accessible; call functions by bare name, e.g. exp(x[0]); "
            f"{self.allowed_summary()})",
        )

    # -- indexing --------------------------------------------------------------------------------------

    def subscript(self, node: ast.Subscript) -> Node:
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
        return Node(index_getter(ident, i), None)

    def slice(self, node: ast.Subscript, ident: str, dim: int, s: ast.Slice) -> Node:
        bounds: list[int | None] = []
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
        return Node(slice_getter(ident, sl), count)

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

    def binop(self, node: ast.BinOp) -> Node:
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
            combined = broadcast_lead([lead, right.lead])
            if isinstance(combined, str):  # "mismatch"
                self.fail(
                    b,
                    f"operands of {symbol!r} in {self.segment(b)!r}{{at}} have incompatible dimensions "
                    f"{lead} and {right.lead}",
                )
            lead = combined
            steps.append((ufunc, right.fn))
        return Node(fold_steps(first.fn, tuple(steps)), lead)

    def binop_ufunc(self, node: ast.BinOp) -> tuple[str, Callable[[Value, Value], Value]]:
        op = type(node.op)
        if op in BINOPS:
            return BINOPS[op]
        symbol = REJECTED_BINOPS.get(op, op.__name__)
        if op is ast.MatMult:
            hint = "matrix multiplication is not supported; write the sum of products explicitly"
        else:
            hint = "bitwise operators are not supported; for logic use 'and', 'or', 'not'"
        self.fail(node, f"operator {symbol!r} in {self.segment(node)!r}{{at}} is not allowed ({hint})")

    def unaryop(self, node: ast.UnaryOp) -> Node:
        operand = self.expr(node.operand)
        if isinstance(node.op, ast.USub):
            return Node(apply1(np.negative, operand.fn), operand.lead)
        if isinstance(node.op, ast.UAdd):
            return operand
        if isinstance(node.op, ast.Not):
            return Node(apply1(logical_not, operand.fn), operand.lead)
        self.fail(
            node,
            f"operator '~' in {self.segment(node)!r}{{at}} is not allowed (bitwise operators are not supported; "
            "for logic use 'not')",
        )

    def compare(self, node: ast.Compare) -> Node:
        operands = [self.expr(node.left)] + [self.expr(c) for c in node.comparators]
        ufuncs = []
        for op in node.ops:
            if type(op) not in COMPARISONS:
                symbol = REJECTED_COMPARISONS.get(type(op), type(op).__name__)
                self.fail(
                    node,
                    f"comparison {symbol!r} in {self.segment(node)!r}{{at}} is not allowed "
                    "(allowed: < <= > >= == !=)",
                )
            ufuncs.append(COMPARISONS[type(op)][1])
        lead = self.combine_leads(node, operands, "comparison")
        fns = tuple(o.fn for o in operands)
        return Node(chained_comparison(tuple(ufuncs), fns), lead)

    def boolop(self, node: ast.BoolOp) -> Node:
        values = [self.expr(v) for v in node.values]
        lead = self.combine_leads(node, values, "'and'" if isinstance(node.op, ast.And) else "'or'")
        ufunc = np.logical_and if isinstance(node.op, ast.And) else np.logical_or
        return Node(logical_chain(ufunc, tuple(v.fn for v in values)), lead)

    def ifexp(self, node: ast.IfExp) -> Node:
        test, body, orelse = self.expr(node.test), self.expr(node.body), self.expr(node.orelse)
        lead = self.combine_leads(node, [test, body, orelse], "conditional expression")
        return Node(apply3(where, test.fn, body.fn, orelse.fn), lead)

    def combine_leads(self, node: ast.AST, parts: Sequence[Node], what: str) -> int | None:
        lead = broadcast_lead([p.lead for p in parts])
        if isinstance(lead, str):  # "mismatch"
            dims = ", ".join("elementwise" if p.lead is None else str(p.lead) for p in parts)
            self.fail(node, f"operands of {what} {self.segment(node)!r}{{at}} have incompatible dimensions ({dims})")
        return lead

    # -- calls -----------------------------------------------------------------------------------------

    def call(self, node: ast.Call) -> Node:
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
                f"function {short(fname)!r}{{at}} is not allowed (allowed functions: {', '.join(FUNCTIONS)})",
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

    def apply_function(self, node: ast.Call, fname: str, spec: Function, args: list[Node]) -> Node:
        if fname in MAX_MIN_FOLD and len(args) >= 2:
            lead = self.combine_leads(node, args, f"{fname}()")
            return Node(fold_args(MAX_MIN_FOLD[fname], tuple(a.fn for a in args)), lead)
        if spec.kind == "reduce":
            (arg,) = args
            if arg.lead is None:
                return Node(apply1(spec.scalar_impl, arg.fn), None)
            return Node(apply1(spec.impl, arg.fn), None)
        lead = self.combine_leads(node, args, f"{fname}()")
        fns = tuple(a.fn for a in args)
        if spec.kind == "fold":
            return Node(fold_args(spec.impl, fns), lead)
        if len(fns) == 1:
            return Node(apply1(spec.impl, fns[0]), lead)
        if len(fns) == 2:
            return Node(apply2(spec.impl, fns[0], fns[1]), lead)
        return Node(apply3(spec.impl, *fns), lead)


#: Node type -> compiler method (each method takes its own node type).
_DISPATCH: dict[type, Callable[[_Compiler, Any], Node]] = {
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
    clean_vars, clean_consts = check_declarations(variables, constants)
    text = check_text(text, max_length)
    tree = parse(text)
    check_size(text, tree)
    compiler = _Compiler(text, len(text) - len(text.lstrip()), clean_vars, clean_consts)
    try:
        assemble, out_dim = compiler.top(tree)
    except RecursionError:  # pragma: no cover - depth is bounded by check_size
        raise ExpressionError(f"expression {shown(text)} is nested too deeply") from None
    return CompiledExpression(text, clean_vars, frozenset(compiler.used), assemble, out_dim)
