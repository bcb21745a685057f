"""A box of numbers is broadcast over the dimensions the dynamics use (docs/spec.md, "Boxes and dimensions"):
a subsystem's dimension is never silently 1 where its dynamics read ``x[1]``."""

import numpy as np
import pytest

from pipelines.errors import SpecError
from pipelines.network import build_network
from pipelines.spec.model import parse_spec

JET = """
name: jet
subsystems:
  - name: jet
    state: {lb: -1, ub: 1, eta: 0.5}
    input: {lb: -1, ub: 1, eta: 1}
    dynamics: "DYNAMICS"
    lipschitz: {x: 2}
specification: {kind: safe, safe: {boxes: [{lb: -0.5, ub: 0.5}]}}
"""


def _network(dynamics, **edits):
    text = JET.replace("DYNAMICS", dynamics)
    for old, new in edits.items():
        text = text.replace(old, new)
    return build_network(parse_spec(text), None)


def test_a_scalar_state_box_takes_the_dimension_the_dynamics_read():
    (s,) = _network("[x[0] + 0.1 * x[1], x[1] - 0.1 * u[0]]").subsystems
    assert s.n == 2 and s.m == 1
    assert np.allclose(s.state_grid.lb, [-1, -1]) and np.allclose(s.state_grid.eta, [0.5, 0.5])
    assert s.state_grid.size == 25


def test_a_list_of_outputs_sets_the_dimension_too():
    (s,) = _network("[x[0], x[0] - u[0]]").subsystems
    assert s.n == 2


def test_a_scalar_input_box_takes_the_inputs_the_dynamics_read():
    (s,) = _network("[x[0] + u[0], x[1] + u[1]]").subsystems
    assert (s.n, s.m) == (2, 2) and s.input_grid.size == 9


def test_lists_say_the_dimension_and_are_not_broadcast():
    with pytest.raises(Exception, match=r"index 1 in 'x\[1\]'.*dimension 1"):
        _network("[x[0], x[1]]", **{"state: {lb: -1, ub: 1, eta: 0.5}": "state: {lb: [-1], ub: [1], eta: [0.5]}"})
    (s,) = _network("x[0] + u[0]").subsystems
    assert (s.n, s.m) == (1, 1)


def test_a_dynamics_that_reads_more_than_it_gives_is_refused_naming_the_field():
    with pytest.raises(SpecError, match=r"subsystems\[0\] \('jet'\)\.state: lb, ub and eta are numbers, so the box is "
                                        r"broadcast over the 2 dimensions dynamics uses \(it reads x\[1\]\), but dynamics "
                                        r"gives 1 component.*write a box per dimension"):
        _network("x[0] + x[1]")


def test_too_many_dimensions_to_broadcast_are_refused():
    with pytest.raises(SpecError, match=r"\.state: .*reads x\[99\].*write a box per dimension"):
        _network("x[99]")


def test_reading_an_internal_variable_not_in_reads_names_reads():
    with pytest.raises(SpecError, match=r"subsystems\[0\] \('jet'\)\.reads: dynamics reads w\[0\], but reads names "
                                        r"none"):
        _network("x[0] + w[0]")
