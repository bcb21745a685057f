"""Hostile expressions (issue 7): payloads meant to escape the whitelist never run.

Every payload of ``tests/test_expr.py``'s ``HOSTILE`` list plus the ones below goes through
:func:`pipelines.expressions.compiler.compile_expression` and, as a subsystem's dynamics and as the interconnection map, through
the spec parser and :func:`pipelines.network.build_network` (where the server compiles them). Each must be
rejected with an :class:`ExpressionError` whose message names the offending token, after work bounded by its
length (Python lines executed and texts parsed are counted, see :func:`tests.conftest.assert_linear_compile`; no
wall-clock time is asserted), and nothing may run: a canary builtin ``__canary__`` and a canary file ``CANARY`` in
the working directory (the payloads' targets) are checked after every payload.
"""

from __future__ import annotations

import builtins

import pytest
import yaml

from pipelines.errors import CompabsError, ExpressionError
from pipelines.expressions import compile_expression
from pipelines.network import build_network
from pipelines.spec.model import parse_spec

from .conftest import EXAMPLES, LINES_FIXED, LINES_PER_CHARACTER, assert_linear_compile, count_work
from .test_expr import HOSTILE, HOSTILE_CONSTS, HOSTILE_VARS
from .trust_log import record

#: Payloads aimed at a side effect (the canary), at the unicode and encoding layer, at size; with the token the
#: rejection must name.
EXTRA: list[tuple[str, str]] = [
    ("__import__('os').system('touch CANARY')", ".system"),
    ("open('CANARY', 'w').write('x')", ".write"),
    ("exec(\"import os; os.system('touch CANARY')\")", "'exec'"),
    ("eval(\"__import__('os').system('touch CANARY')\")", "'eval'"),
    ("[c for c in ().__class__.__base__.__subclasses__() if c.__name__ == 'Popen'][0](['touch', 'CANARY'])",
     "call of '[c for c in"),
    ("x.__class__.__init__.__globals__['__builtins__']['__import__']('os').system('touch CANARY')", ".system"),
    ("__canary__()", "'__canary__'"),
    ("(lambda: __canary__())()", "lambda"),
    ("f\"{__canary__()}\"", "f-string"),
    ("(c := __canary__())", ":="),
    ("[*map(__canary__, x)]", "starred"),
    ("__builtins__.__canary__()", ".__canary__"),
    ("getattr(__builtins__, '__canary__')()", "getattr"),
    ("\uff45\uff58\uff50(x[0])", "U+FF45"),
    ("\uff45\uff56\uff41\uff4c('__canary__()')", "U+FF45"),
    ("__\uff49\uff4d\uff50\uff4f\uff52\uff54__('os')", "U+FF49"),
    ("\u212fxp(x[0])", "U+212F"),
    ("e\u200dxp(x[0])", "U+200D"),
    ("x[0] \u202e+ 1", "U+202E"),
    ("x[0] + \ud800", "U+D800"),
    ("sum(__canary__() for q in x)", "generator expression"),
    ("x[__canary__()]", "'__canary__()'"),
    ("max(x, key=__canary__)", "'key='"),
    ("(yield __canary__())", "'yield'"),
    ("__builtins__['eval']('1')", "__builtins__['eval']"),
    ("exp['x']", "'exp'"),
    ("pi[0]", "'pi' is a scalar constant"),
    ("'__imp' + 'ort__'", "string literal"),
    ("'\\N{LATIN SMALL LETTER A}'", "string literal"),
    ("__debug__", "'__debug__'"),
    ("Ellipsis", "'Ellipsis'"),
    ("help()", "'help'"),
    ("input()", "'input'"),
    ("exit()", "'exit'"),
    ("exp(x[0]) if __canary__() else 0", "'__canary__'"),
    ("x[0] and __canary__()", "'__canary__'"),
    ("x[0] or exec('1')", "'exec'"),
    ("x[0]\n__canary__()", "near '__canary__()'"),
    ("x[0]; __canary__()", "near '; __canary__()'"),
    ("\"\"\"doc\"\"\"", "string literal"),
    ("# -*- coding: utf-7 -*-\n+AF8AXw-import+AF8AXw-('os')", "near \"import"),
    ("x[0:__canary__()]", "slice stop '__canary__()'"),
    ("x[::__canary__()]", "slice step '__canary__()'"),
    ("where(x[0], __canary__, 0)", "'__canary__'"),
    ("clip(x[0], *[0, 1])", "starred argument"),
    ("exp(**{'x': 1})", "'**'"),
    ("(lambda: 0).__code__", ".__code__"),
    ("x.__array_interface__", ".__array_interface__"),
    ("type.__subclasses__(type)", ".__subclasses__"),
    ("np.os.system('id')", ".system"),
    ("numpy.os.system('id')", ".system"),
    ("e.__class__", ".__class__"),
    ("pi.__class__.__mro__", ".__mro__"),
    ("True.__class__", ".__class__"),
    ("1 .real", ".real"),
    ("exp(x[0]).__class__", ".__class__"),
    ("x[0].__class__.__bases__[0].__subclasses__()[0]", "subscript 'x[0].__class__"),
    ("0x" + "f" * 1000, "numeric literal '0xffff"),
    ("1" + "_0" * 100, "numeric literal '1_0_0"),
    ("1e308 * 10", "'1e308'"),
    ("[" * 5000 + "]" * 5000, "10000 characters"),
    ("x" + "[0]" * 100, "nested"),
    ("a" * 3999, "unknown name 'aaaa"),
    ("x[0] if x[0] else __import__", "'__import__'"),
    ("sum((q := x))", ":="),
    ("{**{}}", "dict literal"),
    ("(*x,)", "starred"),
    ("[x for x in x]", "list comprehension"),
    ("async def f(): pass", "near 'async def"),
    ("class A: pass", "near 'class A"),
    ("def f(): return __canary__()", "near 'def f()"),
    ("global x", "near 'global x'"),
    ("print", "'print'"),
    ("__canary__", "'__canary__'"),
    ("__x__", "'__x__'"),
]

#: Arithmetic that a naive evaluator would turn into a huge Python integer (a denial of service): accepted, but
#: evaluated in float64 (inf); as dynamics the result fails the job at the first sample.
RESOURCE: list[str] = ["9**9**9", "10**10**10", "9**9**9**9 * x[0]", "(2**1000)**(2**1000)", "x[0]**9**9**9"]


@pytest.fixture
def canary(monkeypatch, tmp_path):
    """A builtin ``__canary__`` that records calls, and a working directory where ``CANARY`` must not appear."""
    calls: list[int] = []
    monkeypatch.setattr(builtins, "__canary__", lambda *a, **k: calls.append(1) or 0, raising=False)
    monkeypatch.chdir(tmp_path)
    return calls, tmp_path / "CANARY"


def _small_with(field: str, text: str) -> dict:
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    if field == "dynamics":
        data["subsystems"][0]["dynamics"] = text
    else:
        data["interconnection"]["map"] = text
    return data


def test_hostile_payloads_never_run(canary):
    calls, canary_file = canary
    payloads = HOSTILE + EXTRA
    assert len(payloads) >= 150 and len({p for p, _ in payloads}) == len(payloads)
    executed = rejected = 0
    most_lines = 0
    for payload, needle in payloads:
        work = assert_linear_compile(compile_expression, payload, HOSTILE_VARS, HOSTILE_CONSTS)
        if work.error is None:  # pragma: no cover - a payload got through: evaluate it and let the canary tell
            work.result(x=[[1.0], [2.0]], u=[[1.0]], w=[[1.0]])
            pytest.fail(f"payload {payload!r} was accepted")
        message = str(work.error)
        most_lines = max(most_lines, work.lines)
        rejected += 1
        assert needle in message, (payload[:60], message[:300])
        executed += bool(calls) + canary_file.exists()
    assert executed == 0 and not calls and not canary_file.exists()
    record("expressions: hostile payloads (compile_expression)", inputs=len(payloads), executed=executed)
    print(f"{rejected} payloads rejected, at most {most_lines} Python lines each")


@pytest.mark.parametrize("field", ["dynamics", "map"])
def test_hostile_payloads_through_the_spec_never_run(canary, field):
    """As they arrive in a job: a spec field, parsed and built like the server's validation does."""
    calls, canary_file = canary
    payloads = HOSTILE + EXTRA
    named = "subsystem 'agent[0]' dynamics" if field == "dynamics" else "interconnection map"
    # The variables the field is compiled with in small.yaml: an agent's x, u, w; the map's 2 states.
    variables = {"x": 1, "u": 1, "w": 1} if field == "dynamics" else {"x": 2}
    # The work of validating and building small.yaml itself: a payload may add work linear in its length only.
    plain = count_work(lambda: build_network(parse_spec(_small_with(field, "x[0]")), ()),
                       catch=(CompabsError,)).lines
    # A box of numbers takes the dimension its dynamics use (docs/spec.md, boxes and dimensions): through the spec,
    # dynamics reading u[5] are a subsystem with six inputs, and x[0:5] one with five states, not out-of-range indices.
    broadcast = {"u[5]": (1, 6), "x[0:5]": (5, 1)} if field == "dynamics" else {}
    for payload, _ in payloads:
        work = count_work(lambda d: build_network(parse_spec(d), ()), _small_with(field, payload), catch=(CompabsError,))
        if payload in broadcast:
            sub = build_network(parse_spec(_small_with(field, payload)), ()).subsystems[0]
            assert work.error is None and (sub.n, sub.m) == broadcast[payload]
            continue
        if work.error is None:  # pragma: no cover
            pytest.fail(f"payload {payload!r} was accepted as {field}")
        message = str(work.error)
        # Through a spec the text is read twice, each time linearly: the dimensions a box of numbers takes
        # (pipelines/expressions/dimensions.py) and the compile.
        bound = 2 * plain + LINES_FIXED + 2 * LINES_PER_CHARACTER * len(payload)
        assert work.lines <= bound, (payload[:60], work.lines, bound)
        path = "subsystems.0.dynamics" if field == "dynamics" else "interconnection.map"
        if message.startswith("invalid spec:"):
            # The spec model refuses it first (empty text, a lone surrogate), naming the field's path.
            assert path in message and payload in ("", "x[0] + \ud800"), message
            continue
        direct = assert_linear_compile(compile_expression, payload.strip(), variables, {"N": 2.0})  # BlackBox strips it
        assert isinstance(direct.error, ExpressionError), payload[:60]
        # Exactly the compiler's rejection (the token named), prefixed with the field it came in.
        assert message == f"{named}: {direct.error}", (message[:200], str(direct.error)[:200])
    assert not calls and not canary_file.exists()
    record(f"expressions: hostile payloads as spec {field}", inputs=len(payloads), executed=0)


def test_resource_payloads_are_evaluated_in_float64(canary):
    """Powers are float64 operations, never Python integers: checked first on ``2**1100`` (an exact 1100-bit
    integer for Python, ``inf`` in float64), so that a regression fails here instead of hanging on ``9**9**9`` (a
    370-million-digit integer, which no timeout can interrupt: it is one C call)."""
    import numpy as np

    probe = compile_expression("2**1100 + x[0]", {"x": 1})(x=np.zeros((1, 1)))
    assert probe.dtype == np.float64 and probe[0, 0] == np.inf, probe
    for text in RESOURCE:
        f = assert_linear_compile(compile_expression, text, {"x": 1}).result
        out = f(x=np.full((1, 4), 2.0))
        assert out.dtype == np.float64 and not np.isfinite(out).any(), text
        # As dynamics the job fails at the first sample, naming the subsystem and the cell.
        data = _small_with("dynamics", text)
        from pipelines.abstraction.cells import abstract_cells
        from pipelines.errors import BlackBoxError

        sub = build_network(parse_spec(data), ()).subsystems[0]
        with pytest.raises(BlackBoxError, match=r"agent\[0\]' dynamics: returned .*not finite.*state cell \d+, input \d+, internal cell \d+"):
            abstract_cells(sub, 0, 2, 1.76, 0.16, "scp", "paper")
    record("expressions: overflow payloads (float64, finite check)", inputs=len(RESOURCE), executed=0,
           failed_cleanly=len(RESOURCE))
