"""Replicated subsystems whose ``reads`` are expressions in the copy index ``i``: a ring of rooms written once."""

import numpy as np
import pytest

from pipelines.errors import SpecError
from pipelines.interconnection import abstract_interconnection
from pipelines.network import build_network
from pipelines.spec.model import parse_spec
from pipelines.verification.audit import audit_interconnection

# Room temperature in a ring (Dionysos/SCOTS style): each room exchanges heat with its two neighbours, the
# outside (T_e) and a heater (T_h) switched by u in [0, 1].
RING = """
name: ring
parameters: {N: 3, tau: 5, a: 0.05, b: 0.005, c: 0.01, Te: 12, Th: 55}
subsystems:
  - name: room
    replicate: N
    state: {lb: 18, ub: 22, eta: 0.5}
    input: {lb: 0, ub: 1, eta: 0.5}
    reads: ["(i - 1) % N", "(i + 1) % N"]
    dynamics: "x[0] + tau * (a * (w[0] + w[1] - 2 * x[0]) + b * (Te - x[0]) + c * (Th - x[0]) * u[0])"
    lipschitz: {x: 0.88, w: 0.25}
    samples: 4
interconnection:
  map: "x"
  internal: {lb: 18, ub: 22, eta: 0.5}
  error: linear
  samples: 40
  alpha: 0.0001
specification:
  kind: safe
  safe: {boxes: [{lb: 18.5, ub: 21.5}]}
"""


@pytest.mark.parametrize("N", [3, 6])
def test_a_ring_written_once_scales_with_the_parameter(N):
    net = build_network(parse_spec(RING, {"N": N}))
    assert len(net.subsystems) == N and len(net.internal_grids) == N
    assert [s.reads for s in net.subsystems] == [((i - 1) % N, (i + 1) % N) for i in range(N)]
    assert [s.name for s in net.subsystems] == [f"room[{i}]" for i in range(N)]
    # Identical copies share one abstraction: the key leaves the reads out.
    assert len(net.unique_subsystems()) == 1


def test_the_ring_interconnection_is_sound():
    net = build_network(parse_spec(RING))
    ia = abstract_interconnection(net, np.random.default_rng(0))
    assert [list(s) for s in ia.supports] == [[0], [1], [2]]
    result = audit_interconnection(net, ia, 20_000, np.random.default_rng(1))
    assert result.violations == 0


def test_indices_and_expressions_mix():
    net = build_network(parse_spec(RING.replace('"(i - 1) % N", "(i + 1) % N"', '0, "1 + i % 2"')))
    assert [s.reads for s in net.subsystems] == [(0, 1), (0, 2), (0, 1)]
    assert len(net.unique_subsystems()) == 1


def test_a_copy_reading_a_variable_twice_is_named():
    with pytest.raises(SpecError, match=r"reads: repeated internal variable in \[0, 0\] of copy i = 0 \('room\[0\]'\)"):
        build_network(parse_spec(RING.replace('"(i - 1) % N", "(i + 1) % N"', '0, "i"')))


def test_a_single_subsystem_reads_by_expression():
    text = RING.replace("replicate: N", "replicate: 1").replace('"(i - 1) % N", "(i + 1) % N"', '"N - 1", 1')
    text = text.replace('map: "x"', 'map: "[x[0], x[0], x[0]]"')
    net = build_network(parse_spec(text))
    assert net.subsystems[0].reads == (2, 1)


@pytest.mark.parametrize("reads,message", [
    ('["i - 1", "(i + 1) % N"]', r"reads\[0\]: 'i - 1' gives -1 for copy i = 0 \('room\[0\]'\); internal variable "
                                  r"does not exist \(the map has 3 outputs, 0 to 2\)"),
    ('["(i - 1) % N", "i + 1"]', r"reads\[1\]: 'i \+ 1' gives 3 for copy i = 2 \('room\[2\]'\)"),
    ('["i / 2", 0]', r"reads\[0\]: 'i / 2' gives 0.5 for copy i = 1"),
    ('["j", 0]', r"reads\[0\]: .*'j'"),
    ('["x[0]", 0]', r"reads\[0\]: .*'x'"),
    ('["[i, i]", 0]', r"reads\[0\]: '\[i, i\]' has 2 components; an index is one number"),
    ('["", 0]', r"a reads entry is an index or an expression of 1 to 200 characters"),
    ('[5, 0]', r"reads\[0\]: internal variable 5 does not exist"),
])
def test_bad_reads_name_the_entry_and_the_copy(reads, message):
    text = RING.replace('["(i - 1) % N", "(i + 1) % N"]', reads)
    with pytest.raises(SpecError, match=message):
        build_network(parse_spec(text))


def test_a_parameter_named_i_is_refused_with_expression_reads():
    with pytest.raises(SpecError, match="parameter 'i' would hide the copy index"):
        parse_spec(RING.replace("{N: 3,", "{N: 3, i: 1,"))
