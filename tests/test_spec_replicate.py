"""``replicate`` takes an expression over the parameters (``N - 1``), as ``reads`` does: a platoon of a leader
and ``N - 1`` followers is written with one parameter."""

import dataclasses

import pytest

from pipelines.errors import SpecError
from pipelines.network import build_network
from pipelines.spec.costs import Caps, check_spec, subsystem_count
from pipelines.spec.model import parse_spec

PLATOON = """
name: platoon
parameters: {N: 4}
subsystems:
  - name: leader
    state: {lb: 0, ub: 4, eta: 1}
    input: {lb: -1, ub: 1, eta: 1}
    reads: [0]
    dynamics: "0.5 * x[0] + 0.1 * w[0] + u[0]"
    lipschitz: {x: 0.5, w: 0.1}
    samples: 2
  - name: follower
    replicate: N - 1
    state: {lb: 0, ub: 4, eta: 1}
    input: {lb: -1, ub: 1, eta: 1}
    reads: [0]
    dynamics: "0.5 * x[0] + 0.1 * w[0] + u[0]"
    lipschitz: {x: 0.5, w: 0.1}
    samples: 2
interconnection: {map: "x[0]", internal: {lb: 0, ub: 4, eta: 1}, error: linear}
specification: {kind: safe, safe: {boxes: [{lb: 0, ub: 4}]}}
"""


@pytest.mark.parametrize("N", [2, 4, 9])
def test_a_leader_and_n_minus_1_followers(N):
    spec = parse_spec(PLATOON, {"N": N})
    net = build_network(spec)
    assert [s.name for s in net.subsystems] == ["leader"] + [f"follower[{k}]" for k in range(N - 1)]
    assert subsystem_count(spec) == N


def test_the_cap_counts_the_expression_and_names_its_parameter():
    spec = parse_spec(PLATOON, {"N": 1000})
    with pytest.raises(SpecError, match=r"subsystems\[1\]\.replicate \(parameters\.N\): the spec has 1000 subsystems"):
        check_spec(spec, dataclasses.replace(Caps.local(), max_subsystems=10))


@pytest.mark.parametrize("text,match", [
    ("N / 3", r"replicate \('N / 3'\) must be a positive integer, got 1\.33333"),
    ("N - 4", r"must be a positive integer, got 0"),
    ("M - 1", r"replicate 'M - 1'.*unknown name 'M'"),
    ("x[0]", r"replicate 'x\[0\]'.*unknown name 'x'"),
    ("__import__('os')", r"replicate"),
    ("M", r"replicate names parameter 'M', which is not defined"),
])
def test_a_bad_replicate_expression_names_the_field(text, match):
    spec = parse_spec(PLATOON.replace("replicate: N - 1", f"replicate: \"{text}\""))
    with pytest.raises(SpecError, match=match):
        build_network(spec)
