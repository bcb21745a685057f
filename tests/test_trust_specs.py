"""Hypothesis-generated specs (issue 7): accepted, or refused with an error that names the field; nothing else.

Specs are small.yaml with one to three random mutations (a field set to any JSON value, a number set to an
edge value, a field deleted, an unknown field added, an expression replaced by expression-like text), plus
wholly random JSON documents. Through :func:`pipelines.spec.model.parse_spec` and
:func:`pipelines.network.build_network` every one must be accepted or raise a :class:`CompabsError` whose message
names a mutated field; any other exception fails the test. Through ``POST /jobs`` (FastAPI's TestClient, the
real app with its SQLite store, jobs in-process) every response must be 2xx, or 4xx with a JSON ``detail``;
never 5xx. Accepted jobs are cancelled at once (``DELETE /jobs/{id}``) so the campaign runs no real job.

Examples: 1,500 + 1,000 (parser) and 600 (API) per run in the fast share; 6,000 (parser) and 1,200 (API) in
the slow share: 10,300 in all.
"""

from __future__ import annotations

import copy
import json
import math
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipelines.errors import CompabsError
from pipelines.network import build_network
from pipelines.spec.model import JobSpec, parse_spec

from .conftest import EXAMPLES
from .trust_log import record

BASE: dict[str, Any] = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
BASE["options"] = {"seed": 0, "audit_transitions": 0, "synthesis": False}


def _paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, prefix + (i,))
    return out


PATHS = _paths(BASE)


def _at(data: Any, path: tuple) -> Any:
    for p in path:
        data = data[p]
    return data


NUMERIC_PATHS = [p for p in PATHS if isinstance(_at(BASE, p), (int, float)) and not isinstance(_at(BASE, p), bool)]
DICT_PATHS = [()] + [p for p in PATHS if isinstance(_at(BASE, p), dict)]
EXPR_PATHS = [("subsystems", 0, "dynamics"), ("interconnection", "map")]
#: Field names of the spec models (a random document's error must name one of them).
SPEC_FIELDS = {"name", "description", "parameters", "subsystems", "interconnection", "specification", "options"}

JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-(10**20), 10**20) | st.floats() | st.text(max_size=12),
    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=8), c, max_size=4),
    max_leaves=10,
)
EDGE_NUMBERS = st.one_of(
    st.integers(-3, 40),
    st.floats(-1e3, 1e3, allow_nan=False),
    st.sampled_from([0, -0.0, 1e-300, -1e-300, 1e-9, 1e15, 1e300, -1e300, math.inf, -math.inf, math.nan,
                     2**31, 2**63, -(2**63), 10**30, 0.5, 33, 32.000000001]),
    st.lists(st.floats(-50, 50, allow_nan=False), min_size=0, max_size=3),
)
EXPR_TEXT = st.one_of(
    st.text(alphabet=st.sampled_from(list("xuw[]()0123456789+-*/.,<>= eaiflnoprstq_:")), max_size=40),
    st.sampled_from(["x[0]", "mean(x)", "x", "[x[0], x[1]]", "w[0]", "u[0] + x[0]", "sqrt(x[0] - 16)",
                     "1/0", "x[0] * 1e300 * 1e300", "os:system", "tests.nowhere:f", "math:sqrt", "json:dumps",
                     "__import__('os')", "x[5]", "w[1]", "", " "]),
)
MUTATION = st.one_of(
    st.tuples(st.just("set"), st.sampled_from(PATHS), JSON),
    st.tuples(st.just("num"), st.sampled_from(NUMERIC_PATHS), EDGE_NUMBERS),
    st.tuples(st.just("del"), st.sampled_from(PATHS), st.none()),
    st.tuples(st.just("add"), st.sampled_from(DICT_PATHS), st.tuples(st.text(min_size=1, max_size=8), JSON)),
    st.tuples(st.just("expr"), st.sampled_from(EXPR_PATHS), EXPR_TEXT),
)
MUTATED = st.lists(MUTATION, min_size=1, max_size=3)


def mutate(mutations: list[tuple]) -> tuple[Any, set[str]]:
    """Apply mutations to a copy of BASE; return the document and the names an error may use for the fields."""
    data = copy.deepcopy(BASE)
    names: set[str] = set()
    for kind, path, value in mutations:
        try:
            parent = _at(data, path[:-1]) if path else None
            if kind in ("set", "num", "expr"):
                parent[path[-1]] = value
            elif kind == "del":
                del parent[path[-1]]
            else:
                target = _at(data, path)
                target[value[0]] = value[1]
                names.add(value[0])
        except (KeyError, IndexError, TypeError):  # an earlier mutation removed or retyped the parent
            continue
        names |= {p for p in path if isinstance(p, str)}
        if "parameters" in path:
            names |= {"replicate", "parameter"}
        if "reads" in path or "internal" in path or "map" in path:
            names |= {"reads", "internal", "map", "interconnection", "dynamics"}  # outputs vs grids vs readers
        if "kind" in path or "specification" in path:
            names |= {"specification", "target", "safe", "avoid"}
        if "state" in path or "input" in path:
            names |= {"state", "input", "dynamics"}  # a state dimension changes the dynamics' shapes
        if "fixed_points" in path or "controller" in path:
            names |= {"fixed_points", "controller"}
        if path[:1] == ("subsystems",) and len(path) <= 2:
            names |= {"subsystems", "map", "interconnection"}  # fewer or more states change the map's input
    return data, names


def check_parser(data: Any, names: set[str]) -> str:
    """Parse and build; return 'accepted' or 'refused'. Only CompabsError may escape, naming a field."""
    try:
        spec = parse_spec(data)
        build_network(spec, ())
    except CompabsError as exc:
        message = str(exc)
        assert message, "an empty error message"
        assert any(n in message for n in names), f"{message[:400]!r} names none of {sorted(names)}"
        return "refused"
    return "accepted"


COUNTS: dict[str, dict[str, int]] = {}


def _count(label: str, outcome: str) -> None:
    c = COUNTS.setdefault(label, {})
    c[outcome] = c.get(outcome, 0) + 1


def _flush(label: str, **extra: int) -> None:
    c = COUNTS.pop(label, {})
    api = {"4xx": c.get("4xx", 0), "5xx": c.get("5xx", 0)} if "4xx" in c or "2xx" in c else {}
    record(label, inputs=sum(c.values()), **extra, **api)
    print(label, c)


# ============================================================================================ the parser
FAST = settings(max_examples=1500, deadline=None, suppress_health_check=list(HealthCheck))
SLOW = settings(max_examples=6000, deadline=None, suppress_health_check=list(HealthCheck))


def _mutated_specs(label: str):
    @given(MUTATED)
    def run(mutations):
        data, names = mutate(mutations)
        _count(label, check_parser(data, names))

    return run


def test_mutated_specs_through_the_parser():
    label = "specs: mutated small.yaml (parser)"
    FAST(_mutated_specs(label))()
    assert COUNTS[label].get("refused", 0) > 100 and COUNTS[label].get("accepted", 0) > 10, COUNTS[label]
    _flush(label)


@pytest.mark.slow
def test_mutated_specs_through_the_parser_slow_share():
    label = "specs: mutated small.yaml (parser, slow share)"
    SLOW(_mutated_specs(label))()
    _flush(label)


@settings(max_examples=1000, deadline=None, suppress_health_check=list(HealthCheck))
@given(JSON)
def _random_documents(doc):
    names = SPEC_FIELDS | {"mapping", "(spec)", "spec is neither valid YAML nor JSON"}  # the document itself
    _count("specs: random JSON documents (parser)", check_parser(doc, names))


def test_random_documents_through_the_parser():
    _random_documents()
    label = "specs: random JSON documents (parser)"
    assert COUNTS[label].get("accepted", 0) == 0  # no random document is a valid spec
    _flush(label)


def test_the_base_spec_is_valid():
    assert check_parser(copy.deepcopy(BASE), set()) == "accepted"
    assert isinstance(parse_spec(BASE), JobSpec)


# ============================================================================================ POST /jobs
@pytest.fixture(scope="module")
def api(tmp_path_factory):
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.settings import Settings

    data_dir = tmp_path_factory.mktemp("trust-api")
    app = create_app(Settings(data_dir=data_dir, in_process=True, max_concurrent_jobs=1000))
    with TestClient(app, raise_server_exceptions=False) as client:
        yield client


def _post(api, body: bytes, content_type: str, label: str) -> None:
    r = api.post("/jobs", content=body, headers={"content-type": content_type})
    code = r.status_code
    assert code < 500, f"{code} for {body[:300]!r}: {r.text[:300]}"
    if code >= 400:
        assert 400 <= code < 500
        detail = r.json().get("detail")
        assert isinstance(detail, str) and detail, r.text[:300]
        _count(label, "4xx")
    else:
        assert code == 201, r.text[:300]
        job = r.json()
        assert api.delete(f"/jobs/{job['id']}").status_code == 200  # run nothing: cancel at once
        _count(label, "2xx")


def _api_specs(api, label: str):
    @given(MUTATED, st.sampled_from(["json", "yaml"]))
    def run(mutations, fmt):
        data, _ = mutate(mutations)
        try:
            body = json.dumps(data, allow_nan=True).encode() if fmt == "json" else yaml.safe_dump(data).encode()
        except (ValueError, yaml.YAMLError):  # pragma: no cover
            return
        _post(api, body, "application/json" if fmt == "json" else "application/yaml", label)

    return run


def test_mutated_specs_through_post_jobs(api):
    label = "specs: mutated small.yaml (POST /jobs)"
    settings(max_examples=600, deadline=None, suppress_health_check=list(HealthCheck))(_api_specs(api, label))()
    assert COUNTS[label].get("4xx", 0) > 50 and COUNTS[label].get("2xx", 0) > 5, COUNTS[label]
    _flush(label)


@pytest.mark.slow
def test_mutated_specs_through_post_jobs_slow_share(api):
    label = "specs: mutated small.yaml (POST /jobs, slow share)"
    settings(max_examples=1200, deadline=None, suppress_health_check=list(HealthCheck))(_api_specs(api, label))()
    _flush(label)
