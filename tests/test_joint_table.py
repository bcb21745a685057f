"""Inputs drawn at many cells at once from a controller's node table (pipelines/symbolic/joint_table.py) against the
per-cell sampler of exact model counts (pipelines/symbolic/counting.py) on random controllers."""

from __future__ import annotations

import math
from functools import reduce

import numpy as np
import pytest
import yaml

from pipelines.controller import Controller
from pipelines.controller_loading import load_controller
from pipelines.spec.model import parse_spec
from pipelines.symbolic.counting import sampler
from pipelines.symbolic.joint_table import contains, draw, joint_table
from pipelines.symbolic.order import SubsystemLayout
from pipelines.symbolic.relations import state_set
from pipelines.symbolic.symbolic_model import SymbolicModel
from pipelines.verification.closed_loop import _still_allowed, admits
from workers.executors import Execution
from workers.job import run_job

from .conftest import EXAMPLES


def random_controller(seed: int, p: float = 0.3):
    """Three subsystems of 5 cells and 3 inputs (codes 5..7 and 3 invalid), the controller a random set of
    (cell, joint input) pairs; returns the model, the BDD and the membership array (x0, x1, x2, u0, u1, u2)."""
    rng = np.random.default_rng(seed)
    lay = [SubsystemLayout(i, (5,), 3, (), f"k{i}", i, f"s{i}") for i in range(3)]
    m = SymbolicModel(lay, [], order="interleaved", blocks=[2, 0, 1] if seed % 2 else None)
    members = rng.random((5, 5, 5, 3, 3, 3)) < p
    members[:2] = False  # cells outside the domain
    f = m.bdd.false
    for x in np.argwhere(members.any(axis=(3, 4, 5))):
        inputs = [reduce(lambda a, b: a & b, (m.interval(d, int(c), int(c)) for d, c in zip(m.u_digits(), u)))
                  for u in np.argwhere(members[tuple(x)])]
        f |= state_set(m, x[None]) & reduce(lambda a, b: a | b, inputs)
    return m, f, members


def all_cells() -> np.ndarray:
    return np.argwhere(np.ones((5, 5, 5), dtype=bool))


@pytest.mark.parametrize("seed", range(4))
def test_the_first_input_is_the_per_cell_samplers_and_cells_outside_have_none(seed):
    m, f, members = random_controller(seed)
    t = joint_table(m, f & m.u_domain)
    cells = all_cells()
    codes, ok = draw(t, cells, None)
    assert np.array_equal(ok, members.any(axis=(3, 4, 5))[tuple(cells.T)])
    for x, c, has in zip(cells, codes, ok):
        if has:
            cofactor = m.bdd.let(m.state_assignment(x.tolist()), f)
            assert np.array_equal(c, sampler(m, cofactor, m.u_digits()).draw(None))


@pytest.mark.parametrize("seed", range(4))
def test_random_inputs_are_allowed_uniform_and_drawn_as_row_by_row(seed):
    m, f, members = random_controller(seed)
    t = joint_table(m, f & m.u_domain)
    cells = all_cells()
    inside = cells[members.any(axis=(3, 4, 5))[tuple(cells.T)]]
    x = inside[seed % len(inside)]
    codes, ok = draw(t, np.repeat(x[None], 6000, axis=0), np.random.default_rng(seed))
    assert ok.all() and members[(*x, *codes.T)].all()
    hist = np.zeros((3, 3, 3))
    np.add.at(hist, tuple(codes.T), 1)
    allowed = members[tuple(x)]
    expected = 6000 / allowed.sum()
    assert (hist[~allowed] == 0).all() and (hist[allowed] > 0).all()
    assert np.abs(hist[allowed] - expected).max() < 6 * math.sqrt(expected)
    # one call on many cells draws what one call per cell draws
    together, ok = draw(t, cells, np.random.default_rng(seed))
    rng = np.random.default_rng(seed)
    alone = [draw(t, c[None], rng) for c in cells]
    assert np.array_equal(ok, [a[1][0] for a in alone])
    assert np.array_equal(together[ok], np.array([a[0][0] for a in alone])[ok])


@pytest.mark.parametrize("seed", range(2))
def test_contains_is_membership(seed):
    m, f, members = random_controller(seed)
    t = joint_table(m, f & m.u_domain)
    pairs = np.argwhere(np.ones(members.shape, dtype=bool))
    assert np.array_equal(contains(t, pairs[:, :3], pairs[:, 3:]), members[tuple(pairs.T)])


def test_a_share_of_two_to_the_minus_62_is_drawn_exactly():
    """31 subsystems of 2 input bits: at one cell a single joint input (share 4**-31), at another all but one
    (its complement's share 4**-31): kept apart from rounding by counting both polarities."""
    lay = [SubsystemLayout(i, (2,), 4, (), f"k{i}", i, f"s{i}") for i in range(31)]
    m = SymbolicModel(lay, [], order="interleaved")
    one = reduce(lambda a, b: a & b, (m.interval(d, 3, 3) for d in m.u_digits()))
    zeros, ones = np.zeros((1, 31), dtype=np.int64), np.ones((1, 31), dtype=np.int64)
    f = (state_set(m, zeros) & one) | (state_set(m, ones) & ~one)
    t = joint_table(m, f & m.u_domain)
    rng = np.random.default_rng(0)
    codes, ok = draw(t, np.repeat(zeros, 50, axis=0), rng)
    assert ok.all() and (codes == 3).all()
    codes, ok = draw(t, np.repeat(ones, 2000, axis=0), rng)
    assert ok.all() and not (codes == 3).all(axis=1).any()
    assert contains(t, np.concatenate([zeros, ones]), np.full((2, 31), 3)).tolist() == [True, False]
    first, ok = draw(t, ones, None)
    assert ok[0] and first[0].tolist() == [0] * 31


def test_a_bdd_controller_draws_and_checks_inputs_as_its_bdd_says(tmp_path):
    """The platoon's controller is one BDD over states and inputs: its drawn inputs are admissible (the BDD path of
    ``admits``), and the steady choice's check of previous inputs for all rows at once is ``admits`` row by row."""
    data = yaml.safe_load((EXAMPLES / "platoon.yaml").read_text())
    data["options"].update(audit_transitions=0, closed_loop_runs=2, initial_states=[])
    run_job(parse_spec(data), tmp_path / "job", execution=Execution(in_process=True))
    c = load_controller(tmp_path / "job")
    assert type(c) is Controller
    rng = np.random.default_rng(3)
    X = c.state_grid.points(c.sample_cells(40, rng))
    U = c.choose_many(X, rng)
    assert all(u is not None and admits(c, x, u) for x, u in zip(X, U))
    previous: list[np.ndarray | None] = [U[(7 * k) % 40] for k in range(40)]  # others' inputs: some not allowed
    previous[0] = np.asarray(previous[0]) + 1000.0  # off the input grid
    previous[1] = None
    expected = [u is not None and admits(c, x, u) for x, u in zip(X, previous)]
    assert _still_allowed(c, X, previous).tolist() == expected
    assert 0 < sum(expected) < 38
