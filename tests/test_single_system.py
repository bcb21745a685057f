"""A single system: no ``interconnection`` section, no internal variables, every stage still runs."""

import pickle

import numpy as np
import pytest

from pipelines.errors import SpecError
from pipelines.interconnection import abstract_interconnection
from pipelines.network import build_network
from pipelines.spec.model import parse_spec

SINGLE = """
name: single
subsystems:
  - name: plant
    state: {lb: [-1, -1], ub: [1, 1], eta: [0.1, 0.1]}
    input: {lb: -1, ub: 1, eta: 0.5}
    dynamics: "[0.9 * x[0] + 0.1 * x[1], 0.8 * x[1] + 0.2 * u[0]]"
    lipschitz: {x: 1.0}
    samples: 4
specification:
  kind: safe
  safe: {boxes: [{lb: [-0.8, -0.8], ub: [0.8, 0.8]}]}
options: {audit_transitions: 2000, closed_loop_runs: 10}
"""

# The same plant in continuous time: dx/dt = A x + B u with e^{0.1 A} close to the map above. L_x of the sampled
# map is ||e^{0.1 A}||_inf = 0.990 (RK4's matrix is within 1e-6 of it): 1.02 bounds it.
SINGLE_ODE = SINGLE.replace(
    'dynamics: "[0.9 * x[0] + 0.1 * x[1], 0.8 * x[1] + 0.2 * u[0]]"',
    'ode: "[-1.05 * x[0] + 1.05 * x[1], -2.2 * x[1] + 2.2 * u[0]]"\n    sampling_time: 0.1\n    substeps: 4',
).replace("lipschitz: {x: 1.0}", "lipschitz: {x: 1.02}")


def test_a_single_system_has_no_internal_variables():
    net = build_network(parse_spec(SINGLE))
    assert net.internal_grids == () and net.subsystems[0].reads == () and net.subsystems[0].internal_grid is None
    w = net.interconnection_map(np.zeros((5, 2)))
    assert w.shape == (5, 0)
    back = pickle.loads(pickle.dumps(net.interconnection_map))
    assert back(np.zeros((3, 4, 2))).shape == (3, 4, 0)


def test_the_interconnection_stage_yields_an_empty_interconnection():
    net = build_network(parse_spec(SINGLE))
    ia = abstract_interconnection(net, np.random.default_rng(0))
    assert (ia.p, ia.n, ia.nodes, ia.mode) == (0, 2, (), "none")
    x_idx = np.array([[0, 0], [20, 20]])
    assert ia.contains(x_idx, np.zeros((2, 0), dtype=int)).all()
    assert ia.allowed_cells(x_idx) == []


def test_reads_without_an_interconnection_are_refused():
    text = SINGLE.replace("    samples: 4", "    samples: 4\n    reads: [0]")
    with pytest.raises(SpecError, match=r"subsystems\[0\] \('plant'\) read internal variables, which only an "
                                        r"'interconnection' defines"):
        parse_spec(text)


@pytest.mark.parametrize("text", [SINGLE, SINGLE_ODE], ids=["dynamics", "ode"])
def test_a_single_system_runs_end_to_end(tmp_path, text):
    from workers.executors import Execution
    from workers.job import run_job
    from workers.job_audit import audit_job

    report = run_job(parse_spec(text), tmp_path / "job", execution=Execution(in_process=True))
    assert report["interconnection"]["nodes"] == []
    assert report["domain_states"] > 0
    assert report["audit"]["violations"] == 0 and report["audit"]["transitions_checked"] > 0
    assert report["closed_loop"]["runs"] > 0 and report["closed_loop"]["violations"] == 0
    # The stored job reloads: its interconnection has no outputs, and a second audit passes.
    again = audit_job(tmp_path / "job", transitions=1000, seed=3, runs=5, write=False)
    assert again["violations"] == 0


def test_cells_no_controller_can_use_are_not_abstracted():
    """A single system's cells outside the safe set or inside the avoid set are blocking under every input (not
    sampled); every other cell's relation is bit for bit what a full abstraction gives, and so is the domain."""
    from pipelines.abstraction.cells import abstract_cells
    from pipelines.spec.regions import never_winning, spec_regions
    from pipelines.synthesis import explicit
    from workers.job import run_abstraction

    text = SINGLE.replace(
        "specification:\n  kind: safe\n  safe: {boxes: [{lb: [-0.8, -0.8], ub: [0.8, 0.8]}]}",
        "specification:\n  kind: reach_avoid\n  target: {boxes: [{lb: [-0.2, -0.2], ub: [0.2, 0.2]}]}\n"
        "  avoid: {boxes: [{lb: [0.3, -0.1], ub: [0.5, 0.1]}]}\n  safe: {boxes: [{lb: [-0.9, -0.9], ub: [0.9, 0.9]}]}",
    )
    spec = parse_spec(text)
    ab = run_abstraction(spec, audit=False)
    (rel,) = ab.relations.values()
    sub = ab.network.subsystems[0]
    dead = never_winning(spec, ab.network, spec_regions(spec, ab.network))
    assert dead is not None and 0 < dead.sum() < dead.size
    assert ab.report["subsystems"][0]["cells_not_abstracted"] == int(dead.sum())
    full = abstract_cells(sub, 0, sub.state_grid.size, rel.L_x, rel.L_w, sub.spec.growth_bound, sub.spec.scp_objective)
    live = ~dead
    np.testing.assert_array_equal(rel.lo[live], full.lo[live])
    np.testing.assert_array_equal(rel.hi[live], full.hi[live])
    np.testing.assert_array_equal(rel.blocking[live], full.blocking[live])
    assert rel.blocking[dead].all() and (rel.hi[dead] < rel.lo[dead]).all()
    grid = ab.network.composed_state_grid()
    skipped = explicit.solve(explicit.ExplicitGame.from_relation(rel, grid.shape), spec.specification, grid)
    whole = explicit.solve(explicit.ExplicitGame.from_relation(
        type(rel)(rel.method, full.lo, full.hi, full.blocking, rel.L_x, rel.L_w), grid.shape), spec.specification, grid)
    np.testing.assert_array_equal(skipped["reach_avoid"].domain, whole["reach_avoid"].domain)
    np.testing.assert_array_equal(skipped["reach_avoid"].admissible, whole["reach_avoid"].admissible)
    assert skipped["reach_avoid"].domain_states > 0
