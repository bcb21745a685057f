"""The explicit back end (pipelines/synthesis/explicit.py) against the BDD one on random single systems.

Random 1-D to 4-D systems (successor boxes near the state, some blocking pairs) and random specifications: both
solvers must give the same domains, the same controllers (admissible (cell, input) pairs) and, for the fixed
points both count the same way, the same iterations. The array controller must answer as the arrays say, keep
its files intact and become the same BDD controller for the export.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipelines.abstraction.relation import SubsystemRelation
from pipelines.array_controller import ArrayController
from pipelines.errors import CompabsError, SpecError
from pipelines.export.emit import as_bdd
from pipelines.grid import UniformGrid
from pipelines.symbolic.counting import enumerate_cells
from pipelines.symbolic.order import SubsystemLayout
from pipelines.symbolic.relations import state_set, subsystem_relations
from pipelines.symbolic.symbolic_model import SymbolicModel
from pipelines.synthesis import explicit
from pipelines.synthesis.cpre import ControllablePredecessor
from pipelines.synthesis.fixed_points import cobuchi, reach, reach_safe, safe


def random_system(rng: np.random.Generator, dim: int) -> tuple[tuple[int, ...], SubsystemRelation]:
    """A grid of 2-6 cells per coordinate (at most ~400 cells), 1-4 inputs, boxes drifting -1..1 cells with width
    1-2 per coordinate (clipped to the grid), blocking with probability 0.1."""
    shape = tuple(int(k) for k in rng.integers(2, 7 if dim < 4 else 5, size=dim))
    n_x, n_u = math.prod(shape), int(rng.integers(1, 5))
    here = np.stack(np.unravel_index(np.arange(n_x), shape), axis=1).reshape(n_x, 1, 1, dim)
    lo = np.clip(here + rng.integers(-1, 2, size=(n_x, n_u, 1, dim)), 0, np.asarray(shape) - 1)
    hi = np.minimum(lo + rng.integers(0, 2, size=lo.shape), np.asarray(shape) - 1)
    blocking = rng.random((n_x, n_u, 1)) < 0.1
    lo[blocking], hi[blocking] = 0, -1
    return shape, SubsystemRelation("test", lo.astype(np.int32), hi.astype(np.int32), blocking, 1.0, 0.0)


def bdd_game(shape: tuple[int, ...], relation: SubsystemRelation) -> ControllablePredecessor:
    layout = SubsystemLayout(0, shape, relation.blocking.shape[1], (), "k", 0)
    m = SymbolicModel([layout], [])
    T, NB = subsystem_relations(m, {"k": relation})
    return ControllablePredecessor(m, T, NB, {})


def as_cells(m: SymbolicModel, f, shape: tuple[int, ...]) -> np.ndarray:
    rows = enumerate_cells(m, f, m.x_digits())
    out = np.zeros(math.prod(shape), dtype=bool)
    if rows.size:
        out[np.ravel_multi_index(tuple(rows.T), shape)] = True
    return out


def as_pairs(m: SymbolicModel, f, shape: tuple[int, ...], n_u: int) -> np.ndarray:
    rows = enumerate_cells(m, f, m.x_digits() + m.u_digits())
    out = np.zeros((math.prod(shape), n_u), dtype=bool)
    if rows.size:
        out[np.ravel_multi_index(tuple(rows[:, :-1].T), shape), rows[:, -1]] = True
    return out


def bdd_set(m: SymbolicModel, mask: np.ndarray, shape: tuple[int, ...]):
    return state_set(m, np.stack(np.unravel_index(np.flatnonzero(mask), shape), axis=1))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), dim=st.integers(1, 4), with_safe=st.booleans())
def test_both_back_ends_solve_every_specification_alike(seed, dim, with_safe):
    rng = np.random.default_rng(seed)
    shape, relation = random_system(rng, dim)
    n_u = relation.blocking.shape[1]
    game = explicit.ExplicitGame.from_relation(relation, shape)
    assert game.transitions == explicit.transitions(relation)
    cpre = bdd_game(shape, relation)
    m = cpre.model
    n_x = math.prod(shape)
    S, T, A, phi = (rng.random(n_x) < p for p in (0.8, 0.25, 0.15, 0.6))
    bS, bT, bA, bphi = (bdd_set(m, v, shape) for v in (S, T, A, phi))
    safe_set, b_safe = (S, bS) if with_safe else (None, None)
    try:
        e = explicit.safe(game, S)
        b = safe(cpre, bS, local_games=False)
        np.testing.assert_array_equal(e.domain, as_cells(m, b.domain, shape))
        np.testing.assert_array_equal(e.admissible, as_pairs(m, b.controller, shape, n_u))
        assert e.iterations == b.iterations

        for avoid, b_avoid in ((None, None), (A, bA)):
            e = explicit.reach(game, T, avoid, safe_set=safe_set)
            b = reach(cpre, bT, b_avoid, safe=b_safe)
            np.testing.assert_array_equal(e.domain, as_cells(m, b.domain, shape))
            np.testing.assert_array_equal(e.admissible, as_pairs(m, b.controller, shape, n_u))
            assert e.iterations == b.iterations
            layered = reach(cpre, bT, b_avoid, safe=b_safe, layered=True)
            for k, layer in enumerate(layered.layers):  # the layers, set for set
                np.testing.assert_array_equal((e.layer >= 0) & (e.layer <= k), as_cells(m, layer, shape))

        e = explicit.cobuchi(game, phi, safe_set=safe_set)
        b = cobuchi(cpre, bphi, safe=b_safe)
        np.testing.assert_array_equal(e.domain, as_cells(m, b.domain, shape))
        np.testing.assert_array_equal(e.admissible, as_pairs(m, b.controller, shape, n_u))
        assert e.iterations == b.iterations

        e = explicit.reach_safe(game, phi, safe_set=safe_set)
        b = reach_safe(cpre, bphi, safe_set=b_safe, local_games=False)
        np.testing.assert_array_equal(e.domain, as_cells(m, b.domain, shape))
        np.testing.assert_array_equal(e.admissible, as_pairs(m, b.controller, shape, n_u))
    finally:
        cpre.close()


def test_a_reach_controller_makes_progress_on_the_boxes():
    """Every input of a cell of layer k > 0 leads into layers < k (checked on the boxes, not the solver's lists)."""
    rng = np.random.default_rng(7)
    shape, relation = random_system(rng, 3)
    game = explicit.ExplicitGame.from_relation(relation, shape)
    T = rng.random(game.n_x) < 0.2
    r = explicit.reach(game, T)
    assert r.domain_states > T.sum()  # the attractor grew
    for x, u in zip(*np.nonzero(r.admissible)):
        if r.layer[x] == 0:
            continue
        lo, hi = relation.lo[x, u, 0], relation.hi[x, u, 0]
        assert not relation.blocking[x, u, 0]
        box = np.stack(np.meshgrid(*(np.arange(a, b + 1) for a, b in zip(lo, hi)), indexing="ij"), -1).reshape(-1, 3)
        succ = np.ravel_multi_index(tuple(box.T), shape)
        assert np.all((r.layer[succ] >= 0) & (r.layer[succ] < r.layer[x]))


def _controller(rng: np.random.Generator) -> tuple[ArrayController, explicit.ExplicitResult]:
    shape, relation = random_system(rng, 2)
    game = explicit.ExplicitGame.from_relation(relation, shape)
    r = explicit.reach(game, rng.random(game.n_x) < 0.3)
    grid = UniformGrid.covering([0.0] * 2, [k - 1.0 for k in shape], [1.0, 1.0])
    assert grid.shape == shape
    inputs = UniformGrid.inside([0.0], [relation.blocking.shape[1] - 1.0], [1.0])
    meta = {"kind": "reach", "state_grid": grid.describe(), "input_grids": [inputs.describe()]}
    return ArrayController(r.admissible, r.layer, meta), r


def test_the_array_controller_answers_as_its_arrays(tmp_path):
    rng = np.random.default_rng(3)
    ctrl, r = _controller(rng)
    g = ctrl.state_grid
    cells = g.unravel(np.arange(g.size))
    np.testing.assert_array_equal(ctrl.in_domain(cells), r.domain)
    X = g.points(cells)
    chosen = ctrl.choose_many(X, rng)
    first = ctrl.choose_many(X, rng, "first")
    for x, c, f, row in zip(X, chosen, first, r.admissible):
        allowed = ctrl.inputs(x)
        assert (c is None) == (f is None) == (not row.any()) == (allowed.shape[0] == 0)
        if c is not None:
            assert any(np.array_equal(c, a) for a in allowed) and np.array_equal(f, allowed[0])
            assert allowed.shape[0] == row.sum()
    assert ctrl.in_domain(ctrl.sample_cells(50, rng)).all()
    base = cells[0]
    np.testing.assert_array_equal(ctrl.plane_mask(base, 0, 1), r.domain.reshape(g.shape))
    np.testing.assert_array_equal(ctrl.plane_mask(base, 1, 0), r.domain.reshape(g.shape).T)
    # the BDD form is the same controller, cell for cell
    bdd = as_bdd(ctrl)
    m = bdd.model
    np.testing.assert_array_equal(as_pairs(m, bdd.relation, g.shape, r.admissible.shape[1]), r.admissible)


def test_array_controller_files_round_trip_and_refuse_tampering(tmp_path):
    from pipelines.controller_loading import load_controller

    ctrl, r = _controller(np.random.default_rng(5))
    arrays, head = ctrl.save(tmp_path, "controller")
    back = load_controller(tmp_path)
    assert isinstance(back, ArrayController)
    np.testing.assert_array_equal(back.admissible, r.admissible)
    np.testing.assert_array_equal(back.layers, r.layer)
    assert back.meta["kind"] == "reach" and back.meta["form"] == "array"
    data = bytearray(arrays.read_bytes())
    data[len(data) // 2] ^= 0xFF
    arrays.write_bytes(bytes(data))
    with pytest.raises(CompabsError, match="checksum differs"):
        load_controller(tmp_path)
    head.write_text("{not json")
    with pytest.raises(CompabsError, match="not a readable array controller header"):
        ArrayController.load(tmp_path, "controller")


def test_explicit_is_refused_where_it_does_not_apply():
    from pipelines.network import build_network
    from pipelines.spec.model import load_spec

    from .conftest import EXAMPLES

    network = build_network(load_spec(EXAMPLES / "small.yaml"))
    assert explicit.explicit_applicable(network) is not None
    assert explicit.choose_backend("auto", network, {}) == "bdd"
    with pytest.raises(SpecError, match="synthesis_backend is 'explicit', but the network has 2 subsystems"):
        explicit.choose_backend("explicit", network, {})


REACH = """
name: single_reach
subsystems:
  - name: plant
    state: {lb: [-1, -1], ub: [1, 1], eta: [0.1, 0.1]}
    input: {lb: -1, ub: 1, eta: 0.5}
    dynamics: "[0.9 * x[0] + 0.1 * x[1], 0.8 * x[1] + 0.2 * u[0]]"
    lipschitz: {x: 1.0}
    samples: 4
specification:
  kind: reach_avoid
  target: {boxes: [{lb: [-0.3, -0.3], ub: [0.3, 0.3]}]}
  avoid: {boxes: [{lb: [0.4, -0.2], ub: [0.6, 0.2]}]}
options: {audit_transitions: 2000, closed_loop_runs: 20, initial_states: [[0.8, 0.8]]}
"""


@pytest.mark.parametrize("kind", ["safe", "reach_avoid"])
def test_a_job_on_either_back_end_gives_the_same_domain_and_an_exported_c_that_agrees(tmp_path, kind):
    from pipelines.controller_loading import load_controller
    from pipelines.export.emit import export_controller
    from pipelines.spec.model import parse_spec
    from workers.executors import Execution
    from workers.job import run_job

    from .test_export_c import check, compile_driver
    from .test_single_system import SINGLE

    text = SINGLE if kind == "safe" else REACH
    reports, controllers = {}, {}
    for backend in ("explicit", "bdd"):
        spec = parse_spec(text.replace("options: {", f"options: {{synthesis_backend: {backend}, "))
        reports[backend] = run_job(spec, tmp_path / backend, execution=Execution(in_process=True))
        controllers[backend] = load_controller(tmp_path / backend)
    e, b = reports["explicit"], reports["bdd"]
    assert e["synthesis"]["backend"] == "explicit" and b["synthesis"]["backend"] == "bdd"
    assert e["controller"]["form"] == "array" and e["domain_states"] == b["domain_states"] > 0
    assert e["closed_loop"]["violations"] == 0 and e["closed_loop"]["runs"] > 0
    ctrl = controllers["explicit"]
    assert isinstance(ctrl, ArrayController)
    g = ctrl.state_grid
    cells = g.unravel(np.arange(g.size))
    np.testing.assert_array_equal(ctrl.in_domain(cells), controllers["bdd"].in_domain(cells))
    export = export_controller(ctrl)
    check(ctrl, export, compile_driver(export, tmp_path / "c"), np.random.default_rng(0))
    # compabs control answers from the arrays: the admissible inputs, the smallest of them, the layer
    from service.export_cmd import control_at

    inside = g.points(g.unravel(np.flatnonzero(ctrl.domain_mask)[:1]))[0]
    r = control_at(str(tmp_path / "explicit"), ",".join(map(repr, inside.tolist())))
    assert r["in_domain"] and r["inputs"] == ctrl.inputs(inside).tolist() and r["determinized"] == r["inputs"][0]
    assert ("layer" in r) == (kind == "reach_avoid") and r["rule"] == ("earliest_layer" if kind != "safe"
                                                                       else "smallest_index")
    r = control_at(str(tmp_path / "explicit"), "5,5")
    assert not r["in_domain"] and r["reason"] == "outside the state box"


def _reduced(name: str):
    """The field's examples as tests/test_figures_examples.py reduces them (fewer samples, every second input)."""
    import yaml

    from pipelines.spec.model import parse_spec

    from .conftest import EXAMPLES

    data = yaml.safe_load((EXAMPLES / f"{name}.yaml").read_text())
    if name == "dcdc":
        data["subsystems"][0]["samples"] = 4
    else:
        data["subsystems"][0]["input"]["eta"] = 0.6
    return parse_spec(yaml.safe_dump(data))


@pytest.mark.slow
@pytest.mark.timeout(900)
@pytest.mark.parametrize("name", ["dcdc"])
def test_the_examples_domains_are_the_same_set_on_both_back_ends(name):
    """SCOTS's DC-DC example, from one abstraction: the explicit and the BDD fixed points win the same cells (the
    vehicle's are compared by ``bench/run.py --cases general``, whose abstraction takes minutes)."""
    from pipelines.synthesis.synthesize import synthesize
    from workers.job import run_abstraction

    spec = _reduced(name)
    ab = run_abstraction(spec, audit=False)
    grid = ab.network.composed_state_grid()
    (relation,) = ab.relations.values()
    results = explicit.solve(explicit.ExplicitGame.from_relation(relation, grid.shape), spec.specification, grid)
    cpre, bdd_results, _ = synthesize(ab.network, ab.relations, ab.interconnection, spec.specification)
    try:
        assert results.keys() == bdd_results.keys()
        for key, r in bdd_results.items():
            assert r.domain_states == results[key].domain_states > 0
            np.testing.assert_array_equal(as_cells(cpre.model, r.domain, grid.shape), results[key].domain)
    finally:
        cpre.close()
