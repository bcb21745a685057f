"""Tests of the safe-expression compiler (:mod:`pipelines.expressions.compiler`).

Shapes throughout: each variable array is ``(dim, B)``, every result is ``(out_dim, B)`` float64.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipelines.errors import CompabsError, ExpressionError, SpecError
from pipelines.expressions import FUNCTIONS, MAX_DEPTH, MAX_NODES, CompiledExpression, compile_expression

from .conftest import assert_linear_compile

SUB = {"x": 1, "u": 1, "w": 1}  # a subsystem: state, input, internal input
HOSTILE_VARS = {"x": 2, "u": 1, "w": 1}
HOSTILE_CONSTS = {"tau": 0.5}
RNG = np.random.default_rng(12345)


def batch(dim: int, b: int, lo: float = 0.0, hi: float = 10.0) -> np.ndarray:
    """Random array of shape (dim, b)."""
    return RNG.uniform(lo, hi, size=(dim, b))


# --------------------------------------------------------------------------------------------------------
# Correctness
# --------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("b", [1, 1000])
def test_consensus_dynamics(b: int) -> None:
    text = "32/(1+exp(-0.2*(x[0]+u[0]+0.1*(x[0]-w[0])-16)))"
    f = compile_expression(text, SUB)
    x, u, w = batch(1, b), batch(1, b), batch(1, b)
    out = f(x=x, u=u, w=w)
    expected = 32 / (1 + np.exp(-0.2 * (x[0] + u[0] + 0.1 * (x[0] - w[0]) - 16)))
    assert out.shape == (1, b) and out.dtype == np.float64
    np.testing.assert_allclose(out[0], expected, rtol=1e-14)


@pytest.mark.parametrize("b", [1, 1000])
def test_tanks(b: int) -> None:
    text = "(-tau/2 + sqrt(tau**2/4 + x[0] + tau*(u[0]+w[0])))**2"
    f = compile_expression(text, SUB, {"tau": 0.5})
    x, u, w = batch(1, b), batch(1, b), batch(1, b)
    tau = 0.5
    expected = (-tau / 2 + np.sqrt(tau**2 / 4 + x[0] + tau * (u[0] + w[0]))) ** 2
    out = f(x=x, u=u, w=w)
    assert out.shape == (1, b)
    np.testing.assert_allclose(out[0], expected, rtol=1e-14)


@pytest.mark.parametrize("b", [1, 1000])
def test_scalability_min(b: int) -> None:
    f = compile_expression("min(0.75*(x[0]+u[0]), w[0]+1, 32)", SUB)
    x, u, w = batch(1, b, 0, 40), batch(1, b, 0, 40), batch(1, b, 0, 40)
    expected = np.minimum(np.minimum(0.75 * (x[0] + u[0]), w[0] + 1), 32)
    out = f(x=x, u=u, w=w)
    assert out.shape == (1, b)
    np.testing.assert_array_equal(out[0], expected)


@pytest.mark.parametrize("b", [1, 1000])
@pytest.mark.parametrize(
    "text, reference, out_dim",
    [
        ("mean(x)", lambda x: np.mean(x, axis=0)[None], 1),
        ("max(x)", lambda x: np.max(x, axis=0)[None], 1),
        ("min(x)", lambda x: np.min(x, axis=0)[None], 1),
        ("sum(x)", lambda x: np.sum(x, axis=0)[None], 1),
        ("prod(x[0:3])", lambda x: np.prod(x[0:3], axis=0)[None], 1),
        ("norm(x - 5)", lambda x: np.max(np.abs(x - 5), axis=0)[None], 1),
        ("norm2(x)", lambda x: np.linalg.norm(x, axis=0)[None], 1),
        (
            "[0, sqrt(x[0]), (sqrt(x[0])+sqrt(x[1]))/2]",
            lambda x: np.stack([np.zeros_like(x[0]), np.sqrt(x[0]), (np.sqrt(x[0]) + np.sqrt(x[1])) / 2]),
            3,
        ),
        ("where(x[0] > 1, x[0], 0)", lambda x: np.where(x[0] > 1, x[0], 0.0)[None], 1),
        ("2*x", lambda x: 2 * x, 8),
        ("x[1:3]", lambda x: x[1:3], 2),
        ("x[::2] + x[1::2]", lambda x: x[::2] + x[1::2], 4),
        ("x[::-1]", lambda x: x[::-1], 8),
        ("x - mean(x)", lambda x: x - np.mean(x, axis=0), 8),
        ("[x[-1], x[0:2], 7]", lambda x: np.vstack([x[-1], x[0:2], np.full_like(x[0], 7.0)]), 4),
        ("(x[0], x[1])", lambda x: x[0:2], 2),
        ("x[0] + x[1] + x[2] + x[3] + x[4] + x[5] + x[6] + x[7]", lambda x: np.sum(x, axis=0)[None], 1),
    ],
)
def test_interconnection_maps(text: str, reference: Callable[[np.ndarray], np.ndarray], out_dim: int, b: int) -> None:
    f = compile_expression(text, {"x": 8})
    x = batch(8, b)
    out = f(x=x)
    assert f.output_dim() == out_dim
    assert out.shape == (out_dim, b) and out.dtype == np.float64
    np.testing.assert_allclose(out, reference(x), rtol=1e-13)


def _ref_clip(x: np.ndarray) -> np.ndarray:
    return np.clip(x, 2, 5)


@pytest.mark.parametrize(
    "text, reference",
    [
        ("x[0] + 1", lambda x, u: x[0] + 1),
        ("x[0] % 3 + x[0] // 3", lambda x, u: np.mod(x[0], 3) + np.floor_divide(x[0], 3)),
        ("-x[0] ** 2", lambda x, u: -(x[0] ** 2)),
        ("+x[1] - -u[0]", lambda x, u: x[1] + u[0]),
        ("exp2(x[0]) + expm1(u[0]) + log1p(x[1])", lambda x, u: np.exp2(x[0]) + np.expm1(u[0]) + np.log1p(x[1])),
        ("log(x[0]) + log10(x[1]) + log2(u[0])", lambda x, u: np.log(x[0]) + np.log10(x[1]) + np.log2(u[0])),
        ("sin(x[0])*cos(u[0]) - tan(x[1])", lambda x, u: np.sin(x[0]) * np.cos(u[0]) - np.tan(x[1])),
        ("asin(x[0]/10) + arccos(u[0]/10) + atan(x[1]) + arctan(x[0])",
         lambda x, u: np.arcsin(x[0] / 10) + np.arccos(u[0] / 10) + np.arctan(x[1]) + np.arctan(x[0])),
        ("atan2(x[0], u[0]) + arctan2(u[0], x[1])", lambda x, u: np.arctan2(x[0], u[0]) + np.arctan2(u[0], x[1])),
        ("sinh(x[0]/5) + cosh(u[0]/5) + tanh(x[1])", lambda x, u: np.sinh(x[0] / 5) + np.cosh(u[0] / 5) + np.tanh(x[1])),
        ("floor(x[0]) + ceil(u[0]) + sign(x[1] - 5) + abs(u[0] - 5)",
         lambda x, u: np.floor(x[0]) + np.ceil(u[0]) + np.sign(x[1] - 5) + np.abs(u[0] - 5)),
        ("minimum(x[0], u[0]) + maximum(x[1], u[0], 4)",
         lambda x, u: np.minimum(x[0], u[0]) + np.maximum(np.maximum(x[1], u[0]), 4)),
        ("max(x[0], u[0])", lambda x, u: np.maximum(x[0], u[0])),
        ("max(u[0])", lambda x, u: u[0]),
        ("clip(x[0], 2, 5)", lambda x, u: _ref_clip(x[0])),
        ("pow(x[0], 0.5) + hypot(x[1], u[0]) + square(u[0])",
         lambda x, u: np.power(x[0], 0.5) + np.hypot(x[1], u[0]) + np.square(u[0])),
        ("x[0] < u[0]", lambda x, u: (x[0] < u[0]).astype(float)),
        ("1 < x[0] <= 5", lambda x, u: ((1 < x[0]) & (x[0] <= 5)).astype(float)),
        ("x[0] == x[0]", lambda x, u: np.ones_like(x[0])),
        ("x[0] != u[0]", lambda x, u: (x[0] != u[0]).astype(float)),
        ("x[0] > 3 and u[0] < 7", lambda x, u: ((x[0] > 3) & (u[0] < 7)).astype(float)),
        ("x[0] > 3 or u[0] < 7 or x[1] > 9", lambda x, u: ((x[0] > 3) | (u[0] < 7) | (x[1] > 9)).astype(float)),
        ("not x[0] > 3", lambda x, u: (~(x[0] > 3)).astype(float)),
        ("x[0] if x[0] > u[0] else -u[0]", lambda x, u: np.where(x[0] > u[0], x[0], -u[0])),
        ("where(x[0] > u[0], 1, 0) * 2", lambda x, u: np.where(x[0] > u[0], 2.0, 0.0)),
        ("(x[0] > 1) + (x[0] > 2)", lambda x, u: (x[0] > 1).astype(float) + (x[0] > 2).astype(float)),
        ("-(x[0] > 1)", lambda x, u: -(x[0] > 1).astype(float)),
        ("pi * e + True - False", lambda x, u: np.full_like(x[0], np.pi * np.e + 1)),
        ("1_000 + 0x10 + 1e3 + .5", lambda x, u: np.full_like(x[0], 1000 + 16 + 1000 + 0.5)),
        ("x[0] # a trailing comment", lambda x, u: x[0]),
        ("(x[0] +\n u[0])", lambda x, u: x[0] + u[0]),
        ("  x[0]  ", lambda x, u: x[0]),
        ("-2 ** 2 + 0 * x[0]", lambda x, u: np.full_like(x[0], -4.0)),
        ("2 ** -1 * x[0]", lambda x, u: 0.5 * x[0]),
    ],
)
def test_elementwise_against_numpy(text: str, reference: Callable[..., np.ndarray]) -> None:
    f = compile_expression(text, {"x": 2, "u": 1})
    x, u = batch(2, 50, 0.1, 9.9), batch(1, 50, 0.1, 9.9)
    out = f(x=x, u=u)
    assert out.shape == (1, 50) and out.dtype == np.float64
    np.testing.assert_allclose(out[0], reference(x, u), rtol=1e-13)


def test_constants_are_broadcast_in_lists_and_scalars() -> None:
    f = compile_expression("[1, N, tau*2]", {"x": 1}, {"tau": 0.5, "N": 8})
    out = f(x=np.zeros((1, 4)))
    np.testing.assert_array_equal(out, [[1] * 4, [8] * 4, [1] * 4])
    g = compile_expression("3", {"x": 1})
    np.testing.assert_array_equal(g(x=np.zeros((1, 5))), np.full((1, 5), 3.0))


def test_vector_variable_of_dim_one_and_output_is_a_fresh_array() -> None:
    f = compile_expression("x", {"x": 1})
    x = np.arange(5.0)[None]
    out = f(x=x)
    assert out.shape == (1, 5)
    out[0, 0] = 99.0
    assert x[0, 0] == 0.0  # the result never aliases an input


def test_integer_and_list_inputs_are_converted_to_float64() -> None:
    f = compile_expression("x[0] / 2", {"x": 1})
    out = f(x=[[1, 2, 3]])
    assert out.dtype == np.float64
    np.testing.assert_array_equal(out, [[0.5, 1.0, 1.5]])


def test_single_underscore_names_like_spec_parameters() -> None:
    f = compile_expression("_k * x_1[0]", {"x_1": 1}, {"_k": 3})
    np.testing.assert_array_equal(f(x_1=np.ones((1, 2))), [[3.0, 3.0]])


def test_unused_declared_variables_may_be_omitted() -> None:
    f = compile_expression("x[0] + 1", SUB)
    np.testing.assert_array_equal(f(x=np.ones((1, 2))), [[2.0, 2.0]])


def test_output_dim_is_static_and_matches_evaluation() -> None:
    for text, dim in [("x[0]", 1), ("x", 3), ("[x, x[0]]", 4), ("x[0:2] * 2", 2), ("sum(x)", 1), ("[1,2,3,4,5]", 5)]:
        f = compile_expression(text, {"x": 3})
        assert f.output_dim() == dim
        assert f(x=np.ones((3, 2))).shape == (dim, 2)


def test_public_attributes_are_read_only() -> None:
    f = compile_expression("x[0]", {"x": 2})
    assert isinstance(f, CompiledExpression)
    assert f.text == "x[0]" and f.variables == {"x": 2}
    with pytest.raises(AttributeError):
        f.text = "other"  # type: ignore[misc]
    f.variables["x"] = 5
    assert f.variables == {"x": 2}


def test_overflow_is_inf_not_a_big_int() -> None:
    # float64 powers first: with Python ints 2**1100 is exact (and 9**9**9 below would never return).
    assert compile_expression("2**1100 + x[0]", SUB)(x=np.zeros((1, 1)))[0, 0] == np.inf
    f = compile_expression("9**9**9", SUB)
    out = f(x=np.ones((1, 3)))
    assert out.dtype == np.float64
    assert out.shape == (1, 3) and np.all(np.isposinf(out))
    g = compile_expression("10**400 + x[0]", SUB)
    assert np.all(np.isposinf(g(x=np.ones((1, 2)))))


def test_nan_and_inf_are_returned_silently() -> None:
    f = compile_expression("[log(x[0] - 10), 1/(x[0]-x[0]), sqrt(-x[0]), 0/0]", {"x": 1})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = f(x=np.ones((1, 2)))
    assert np.all(np.isnan(out[0])) and np.all(np.isinf(out[1])) and np.all(np.isnan(out[2:]))


def test_nan_is_truthy_like_python() -> None:
    f = compile_expression("where(x[0], 1, 2) + (not x[0])", {"x": 1})
    np.testing.assert_array_equal(f(x=np.array([[np.nan, 0.0, 3.0]])), [[1.0, 3.0, 1.0]])


def test_long_sums_are_not_limited_by_depth() -> None:
    text = " + ".join(f"x[{i % 8}]" for i in range(400))
    f = compile_expression(text, {"x": 8})
    x = batch(8, 10)
    np.testing.assert_allclose(f(x=x)[0], 50 * np.sum(x, axis=0), rtol=1e-12)


def test_depth_limit_counts_real_nesting() -> None:
    ok = "(" * 30 + "x[0]" + ")" * 30
    compile_expression(ok, {"x": 1})
    with pytest.raises(ExpressionError, match="nested"):
        compile_expression("exp(" * (MAX_DEPTH + 1) + "x[0]" + ")" * (MAX_DEPTH + 1), {"x": 1})
    with pytest.raises(ExpressionError, match="nested"):
        compile_expression("2**" * (MAX_DEPTH + 1) + "x[0]", {"x": 1})


def test_node_limit() -> None:
    text = "+".join(["x"] * (MAX_NODES // 2 + 10))
    with pytest.raises(ExpressionError, match=f"more than {MAX_NODES} syntax nodes"):
        compile_expression(text, {"x": 1})


def test_every_whitelisted_function_compiles_and_runs() -> None:
    for name, spec in FUNCTIONS.items():
        n = spec.min_args
        args = ", ".join(["x[0]"] * n)
        f = compile_expression(f"{name}({args})", {"x": 1})
        assert f(x=np.full((1, 3), 0.5)).shape == (1, 3), name


def test_pipelines_errors_hierarchy() -> None:
    assert issubclass(ExpressionError, SpecError) and issubclass(ExpressionError, CompabsError)


# --------------------------------------------------------------------------------------------------------
# Rejections that are not hostile: user mistakes get helpful messages
# --------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "text, variables, needle",
    [
        ("x[0:3] + x[3:5]", {"x": 8}, "incompatible dimensions 3 and 2"),
        ("[x[0:3], 1] + 1", {"x": 8}, "nested list"),
        ("where(x[0:2], x[0:3], 0)", {"x": 8}, "incompatible dimensions"),
        ("y[0]", {"x": 1}, "unknown name 'y'"),
        ("y", {"x": 1}, "allowed names: x, pi, e"),
        ("sum(x, x)", {"x": 2}, "'sum' at column 1 takes 1 argument, got 2"),
        ("where(x[0] > 0, 1)", {"x": 1}, "'where' at column 1 takes 3 arguments, got 2"),
        ("max()", {"x": 1}, "'max' at column 1 takes 1 or more arguments, got 0"),
        ("minimum(x[0])", {"x": 1}, "'minimum' at column 1 takes 2 or more arguments, got 1"),
        ("1if x[0] else 2", {"x": 1}, "invalid decimal literal"),
        ("(x[0] +\n", {"x": 1}, "syntax error"),
    ],
)
def test_user_errors(text: str, variables: dict[str, int], needle: str) -> None:
    with pytest.raises(ExpressionError) as info:
        compile_expression(text, variables)
    assert needle in str(info.value)


@pytest.mark.parametrize(
    "variables, constants, needle",
    [
        ({"x": 0}, None, "positive integer dimension"),
        ({"x": 1.5}, None, "positive integer dimension"),
        ({"x": True}, None, "positive integer dimension"),
        ({"__x": 1}, None, "'__x' is not allowed"),
        ({"1x": 1}, None, "'1x' is not allowed"),
        ({"__class__": 1}, None, "'__class__' is not allowed"),
        ({"lambda": 1}, None, "'lambda' is not allowed"),
        ({"x y": 1}, None, "'x y' is not allowed"),
        ({"exp": 1}, None, "clashes with the function"),
        ({"e": 1}, None, "clashes with the built-in constant"),
        ({"x": 1}, {"x": 2.0}, "same name as a variable"),
        ({"x": 1}, {"k": float("nan")}, "finite real number"),
        ({"x": 1}, {"k": "1"}, "finite real number"),
        ({"x": 1}, {"pi": 3.0}, "clashes with the built-in constant"),
    ],
)
def test_bad_declarations(variables: dict, constants: dict | None, needle: str) -> None:
    with pytest.raises(ExpressionError) as info:
        compile_expression("1", variables, constants)
    assert needle in str(info.value)


@pytest.mark.parametrize(
    "arrays, needle",
    [
        ({"x": np.ones((2, 3)), "y": np.ones((1, 3))}, "unknown variable 'y'"),
        ({"x": np.ones((2, 3))}, "variable 'u' was not passed"),
        ({"x": np.ones(3), "u": np.ones((1, 3))}, "must have shape (2, B)"),
        ({"x": np.ones((3, 3)), "u": np.ones((1, 3))}, "must have shape (2, B)"),
        ({"x": np.ones((2, 3)), "u": np.ones((1, 4))}, "batch size 4"),
        ({"x": np.ones((2, 3)), "u": [["a", "b", "c"]]}, "not a real float array"),
        ({"x": np.ones((2, 3)) * 1j, "u": np.ones((1, 3))}, "complex"),
    ],
)
def test_bad_call_arguments(arrays: dict, needle: str) -> None:
    f = compile_expression("x[0] + u[0]", {"x": 2, "u": 1})
    with pytest.raises(ExpressionError) as info:
        f(**arrays)
    assert needle in str(info.value)


def test_call_without_any_array() -> None:
    with pytest.raises(ExpressionError, match="batch size"):
        compile_expression("1", {"x": 1})()


# --------------------------------------------------------------------------------------------------------
# Hostile payloads: every one is an ExpressionError (never another type), fast, naming the culprit
# --------------------------------------------------------------------------------------------------------

HOSTILE: list[tuple[str, str]] = [
    # dunder chains, attribute access
    ("().__class__.__bases__[0].__subclasses__()", ".__subclasses__"),
    ("().__class__", ".__class__"),
    ("x.__class__", ".__class__"),
    ("x.__class__.__mro__[1]", ".__mro__"),
    ("x.T", ".T"),
    ("x[0].real", ".real"),
    ("pi.real", ".real"),
    ("exp.__globals__", ".__globals__"),
    ("exp.__globals__['__builtins__']", "exp.__globals__"),
    ("x[0] if x[0] else x.__dict__", ".__dict__"),
    ("x.sum()", ".sum"),
    # calls of non-whitelisted names
    ("__import__('os').system('id')", ".system"),
    ("__import__('os')", "'__import__'"),
    ("__import__", "unknown name '__import__'"),
    ("eval('1')", "'eval'"),
    ("exec('print(1)')", "'exec'"),
    ("compile('1', '', 'eval')", "'compile'"),
    ("open('/etc/passwd')", "'open'"),
    ("getattr(x, 'T')", "'getattr'"),
    ("globals()", "'globals'"),
    ("type(x)", "'type'"),
    ("print(1)", "'print'"),
    ("breakpoint()", "'breakpoint'"),
    ("foo(x)", "'foo'"),
    ("(lambda q: q)(1)", "lambda"),
    ("exp(x)[0]", "'exp(x)[0]'"),
    # names
    ("__builtins__", "'__builtins__'"),
    ("x[0] if True else __builtins__", "'__builtins__'"),
    ("exp", "must be called"),
    ("None", "'None'"),
    # lambdas, comprehensions, f-strings
    ("lambda: 1", "lambda"),
    ("1 if x[0] else (lambda: 0)", "lambda"),
    ("[q for q in x]", "list comprehension"),
    ("sum([q for q in x])", "list comprehension"),
    ("{q for q in x}", "set comprehension"),
    ("{q: q for q in x}", "dict comprehension"),
    ("sum(q for q in x)", "generator expression"),
    ("f'{x}'", "f-string"),
    ("f'{x.__class__}'", "f-string"),
    # literals
    ("'a'", "string literal"),
    ("b'a'", "bytes literal"),
    ("1j", "complex literal"),
    ("...", "ellipsis"),
    ("{1, 2}", "set literal"),
    ("{'a': 1}", "dict literal"),
    ("[[x[0]]]", "nested list"),
    ("[x[0], (u[0], w[0])]", "nested tuple"),
    ("[]", "empty list"),
    ("1e400", "'1e400'"),
    ("-1e16", "'1e16'"),
    ("100000000000000000000000", "'100000000000000000000000'"),
    ("1" + "0" * 400, "'1000000000"),
    # operators
    ("x[0] & u[0]", "'&'"),
    ("x[0] | u[0]", "'|'"),
    ("x[0] ^ u[0]", "'^'"),
    ("x[0] << 1", "'<<'"),
    ("x[0] >> 1", "'>>'"),
    ("~x[0]", "'~'"),
    ("x @ x", "'@'"),
    ("x[0] is u[0]", "'is'"),
    ("x[0] in x", "'in'"),
    ("x[0] not in x", "'not in'"),
    # walrus, starred, keywords
    ("(y:=1)", ":="),
    ("[*x]", "starred"),
    ("sum(*x)", "starred"),
    ("clip(x[0], a_min=0, a_max=1)", "'a_min='"),
    ("exp(x=1)", "'x='"),
    ("max(**{})", "'**'"),
    # subscripts
    ("x[y]", "'y'"),
    ("x[u[0]]", "'u[0]'"),
    ("x[0][0]", "'x[0][0]'"),
    ("u[5]", "index 5"),
    ("x[-3]", "index -3"),
    ("x[0.5]", "'0.5'"),
    ("x[True]", "'True'"),
    ("x[0, 1]", "'0, 1'"),
    ("tau[0]", "'tau' is a scalar constant"),
    ("x[0:tau]", "slice stop 'tau'"),
    ("x[u[0]:]", "slice start 'u[0]'"),
    ("x[::0]", "slice step 0"),
    ("x[0:5]", "slice stop 5"),
    ("x[1:1]", "selects no components"),
    # generators, coroutines, statements
    ("(yield)", "'yield'"),
    ("(yield from x)", "'yield from'"),
    ("await x", "'await'"),
    ("x = 1", "near '= 1'"),
    ("x[0]; x[1]", "near '; x[1]'"),
    ("x[0]\nimport os", "near 'import os'"),
    ("import os", "near 'import os'"),
    ("del x", "near 'del x'"),
    ("x if x[0] else", "syntax error"),
    # unicode look-alikes, control characters
    ("\u0445[0]", "U+0445"),
    ("\uff58[0]", "U+FF58"),
    ("x[0] + \u0455qrt(x[0])", "U+0455"),
    ("x\x00", "U+0000"),
    ("x[0]\x0bimport os", "U+000B"),
    ("x[0]\x7f", "U+007F"),
    # size and nesting
    ("(" * 200 + "x[0]" + ")" * 200, "nested"),
    ("-" * 5000 + "x[0]", "is 5004 characters, the limit is 4000"),
    ("-" * 3990 + "x[0]", "nested"),
    ("-" * 100 + "x[0]", "nested"),
    ("not " * 100 + "x[0]", "nested"),
    ("x" * 4001, "is 4001 characters, the limit is 4000"),
    ("x+" * 1100 + "x", f"more than {MAX_NODES} syntax nodes"),
    ("", "is empty"),
    ("   \n\t ", "is empty"),
]


def test_enough_hostile_payloads() -> None:
    assert len(HOSTILE) >= 60
    assert len({p for p, _ in HOSTILE}) == len(HOSTILE)


@pytest.mark.parametrize("payload, needle", HOSTILE, ids=[f"hostile{i}" for i in range(len(HOSTILE))])
def test_hostile_payload_is_rejected(payload: str, needle: str) -> None:
    try:
        compile_expression(payload, HOSTILE_VARS, HOSTILE_CONSTS)
    except ExpressionError as exc:
        message = str(exc)
    except BaseException as exc:  # pragma: no cover - the test fails with the wrong type named
        pytest.fail(f"{type(exc).__name__} instead of ExpressionError: {exc}")
    else:  # pragma: no cover
        pytest.fail(f"payload {payload!r} was accepted")
    assert_linear_compile(compile_expression, payload, HOSTILE_VARS, HOSTILE_CONSTS)  # work linear in its length
    assert needle in message, message
    assert message.startswith("expression "), message


def test_compile_time_is_bounded_at_the_length_limit() -> None:
    payloads = [
        "x[0]+" * 799 + "x[0]",
        "(" * 60 + "x[0]" + ")" * 60 + "+1" * 1900,
        "-" * 3995 + "x",
        "1" * 4000,
        "((((" * 15 + "x" + "))))" * 15 + "*x" * 1900,
        "x" + "[0]" * 1332,
        "[" + ",".join(["x[0]"] * 799) + "]",
    ]
    for p in payloads:
        assert len(p) <= 4000
        assert_linear_compile(compile_expression, p, {"x": 1})


# --------------------------------------------------------------------------------------------------------
# Property tests
# --------------------------------------------------------------------------------------------------------

EXPR_ALPHABET = st.sampled_from(list("xuw[]():,.0123456789+-*/%<>=!&|^~@ eaiflnoprstq'\"_{}\n;#\\") + ["\u0445", "\uff58"])


def _try(text: str) -> None:
    """Compile ``text``; if it compiles, evaluate it. Only ExpressionError may escape."""
    try:
        f = compile_expression(text, HOSTILE_VARS, HOSTILE_CONSTS)
    except ExpressionError:
        return
    out = f(x=np.ones((2, 3)), u=np.ones((1, 3)), w=np.ones((1, 3)))
    assert out.shape == (f.output_dim(), 3) and out.dtype == np.float64


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.text(max_size=300))
def test_random_text_only_raises_expression_error(text: str) -> None:
    _try(text)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.text(alphabet=EXPR_ALPHABET, max_size=120))
def test_random_expression_like_text_only_raises_expression_error(text: str) -> None:
    _try(text)


Ref = Callable[[np.ndarray, np.ndarray], np.ndarray]
BIN = {"+": np.add, "-": np.subtract, "*": np.multiply, "/": np.true_divide, "**": np.power, "%": np.mod}
UNARY = {"exp": np.exp, "sin": np.sin, "tanh": np.tanh, "abs": np.abs, "sqrt": np.sqrt, "log1p": np.log1p}


def _leaf_index(i: int) -> tuple[str, Ref]:
    return f"x[{i}]", lambda x, u: x[i]


def _leaf_const(c: float) -> tuple[str, Ref]:
    return f"({c!r})", lambda x, u: np.float64(c)  # parenthesised: -2.0 ** x is -(2.0 ** x) in Python


def _binop(t: tuple[tuple[str, Ref], str, tuple[str, Ref]]) -> tuple[str, Ref]:
    (ta, fa), op, (tb, fb) = t
    ufunc = BIN[op]
    return f"({ta} {op} {tb})", lambda x, u: ufunc(fa(x, u), fb(x, u))


def _call(t: tuple[str, tuple[str, Ref]]) -> tuple[str, Ref]:
    name, (ta, fa) = t
    ufunc = UNARY[name]
    return f"{name}({ta})", lambda x, u: ufunc(fa(x, u))


def _neg(t: tuple[str, Ref]) -> tuple[str, Ref]:
    ta, fa = t
    return f"(-{ta})", lambda x, u: np.negative(fa(x, u))


def _compare(t: tuple[tuple[str, Ref], tuple[str, Ref]]) -> tuple[str, Ref]:
    (ta, fa), (tb, fb) = t
    return f"({ta} < {tb})", lambda x, u: np.less(fa(x, u), fb(x, u)).astype(np.float64)


LEAVES = st.one_of(
    st.integers(min_value=-2, max_value=1).map(_leaf_index),
    st.just(("u[0]", lambda x, u: u[0])),
    st.floats(min_value=-100, max_value=100, allow_nan=False).map(_leaf_const),
)
ARITH = st.recursive(
    LEAVES,
    lambda children: st.one_of(
        st.tuples(children, st.sampled_from(sorted(BIN)), children).map(_binop),
        st.tuples(st.sampled_from(sorted(UNARY)), children).map(_call),
        children.map(_neg),
        st.tuples(children, children).map(_compare),
    ),
    max_leaves=25,
)


@settings(max_examples=300, deadline=None)
@given(ARITH, st.integers(min_value=1, max_value=7))
def test_random_arithmetic_matches_numpy(expr: tuple[str, Ref], b: int) -> None:
    text, reference = expr
    f = compile_expression(text, {"x": 2, "u": 1})
    x, u = RNG.normal(size=(2, b)) * 3, RNG.normal(size=(1, b)) * 3
    out = f(x=x, u=u)
    with np.errstate(all="ignore"):
        expected = np.broadcast_to(reference(x, u), (b,))
    assert out.shape == (1, b)
    np.testing.assert_allclose(out[0], expected, rtol=1e-12, atol=0, equal_nan=True)


# --------------------------------------------------------------------------------------------------------
# Batches of several axes (a grid of samples passed as broadcast views)
# --------------------------------------------------------------------------------------------------------


def test_batches_of_several_axes_broadcast_like_the_materialised_arrays() -> None:
    f = compile_expression("[x[0] * u[0] + sin(w[1]), max(x[1], w[0]), norm(x - w)]", {"x": 2, "u": 1, "w": 2})
    rng = np.random.default_rng(0)
    x, u, w = rng.normal(size=(2, 4, 1, 5)), rng.normal(size=(1, 5)), rng.normal(size=(2, 3, 5))
    out = f(x=x, u=u, w=w)
    assert out.shape == (3, 4, 3, 5)

    def flat(a):  # batch axes right-aligned with (4, 3, 5), then materialised
        a = a.reshape(a.shape[:1] + (1,) * (4 - a.ndim) + a.shape[1:])
        return np.broadcast_to(a, (a.shape[0], 4, 3, 5)).reshape(a.shape[0], -1)

    np.testing.assert_array_equal(out.reshape(3, -1), f(x=flat(x), u=flat(u), w=flat(w)))
    single = compile_expression("x[0] + 1", {"x": 2})(x=x)  # an elementwise result, returned without a copy
    assert single.shape == (1, 4, 1, 5) and single.flags.writeable
    np.testing.assert_array_equal(single[0], x[0] + 1)
    assert not np.shares_memory(compile_expression("x[0]", {"x": 2})(x=x), x)  # never a view of an argument


def test_batch_shapes_that_do_not_broadcast_are_refused() -> None:
    f = compile_expression("x[0] + u[0]", {"x": 1, "u": 1})
    with pytest.raises(ExpressionError, match="batch shape .* does not broadcast"):
        f(x=np.ones((1, 4, 3)), u=np.ones((1, 4, 2)))
