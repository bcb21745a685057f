"""Specifications with a safe set (reach, reach-avoid and reach-and-stay within ``S``), several obstacles, and
what a synthesis says when its domain is empty (docs/method.md §6).

The fixed points are checked on hand-made integrators, where the effect of ``S`` is known by hand, and against
the explicit-state solver of :mod:`tests.test_synthesis` on random networks; the closed loop on a concrete
2-D integrator with two obstacles.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipelines.errors import SpecError
from pipelines.grid import UniformGrid
from pipelines.spec.model import Region, parse_spec
from pipelines.spec.regions import abstract_region
from pipelines.symbolic.order import SubsystemLayout
from pipelines.symbolic.relations import region, state_set
from pipelines.synthesis.fixed_points import cobuchi, reach, reach_and_stay, reach_avoid, reach_safe, safe

from .games import (
    Explicit,
    Net,
    build,
    cells,
    check_progress,
    check_stay,
    controller_matrix,
    integrator_spec,
    integrators,
    layered_matrix,
    random_net,
    random_set,
    states_vector,
)
from .strategies import grid

BOX = {"lb": 0, "ub": 1}


# ============================================================================ the spec model
@pytest.mark.parametrize("kind", ["reach", "reach_avoid", "reach_and_stay"])
def test_every_kind_takes_an_optional_safe_set(kind):
    spec = {"kind": kind, "target": {"boxes": [BOX]}, "safe": {"boxes": [{"lb": 0, "ub": 5}]}}
    if kind == "reach_avoid":
        spec["avoid"] = {"boxes": [{"lb": 2, "ub": 3}, {"lb": 4, "ub": 4.5}]}
    parsed = parse_spec(integrator_spec(spec))
    assert parsed.specification.safe is not None and parsed.specification.safe.boxes[0].ub == 5


@pytest.mark.parametrize("specification,match", [
    ({"kind": "reach", "target": {"boxes": [BOX]}, "avoid": {"boxes": [BOX]}}, "'avoid' belongs to kind 'reach_avoid'"),
    ({"kind": "reach_and_stay", "target": {"boxes": [BOX]}, "avoid": {"boxes": [BOX]}}, "has no 'avoid' set"),
    ({"kind": "safe", "safe": {"boxes": [BOX]}, "target": {"boxes": [BOX]}}, "a 'safe' specification has no 'target'"),
    ({"kind": "safe", "target": {"boxes": [BOX]}}, "needs 'safe'"),
    ({"kind": "reach_avoid", "target": {"boxes": [BOX]}}, "needs 'avoid'"),
])
def test_a_region_the_kind_does_not_use_is_refused_not_ignored(specification, match):
    with pytest.raises(SpecError, match=match):
        parse_spec(integrator_spec(specification))


def members(game, f, K: int) -> list[int]:
    return sorted(int(v) for v in states_vector(game.model, f, Explicit(integrators((K,)))).nonzero()[0])


def test_a_safe_set_cuts_a_line_where_it_has_a_gap():
    """On a line 0..9 with steps of one cell, T = {9}: without S every cell reaches T; S without cell 5 cuts the
    line, and only 6..9 reach T inside S (by hand). Avoiding 5 is the same; S and A together cut twice."""
    K = 10
    game = build(integrators((K,)), "interleaved")
    T, gap = cells(game, 9), cells(game, 5)
    S = game.model.x_domain & ~gap
    for layered in (False, True):
        plain = reach(game, T, layered=layered)
        assert members(game, plain.domain, K) == list(range(10)) and plain.iterations == 10
        within = reach(game, T, safe=S, layered=layered)
        assert members(game, within.domain, K) == [6, 7, 8, 9] and within.iterations == 4
        avoided = reach_avoid(game, T, gap, layered=layered)
        assert members(game, avoided.domain, K) == [6, 7, 8, 9]
        both = reach_avoid(game, T, cells(game, 7), safe=S, layered=layered)
        assert members(game, both.domain, K) == [8, 9]
    # A target outside S does not count: the run would leave S on arrival.
    assert members(game, reach(game, T | gap, safe=S).domain, K) == [6, 7, 8, 9]


def test_reach_and_stay_within_a_safe_set_by_hand():
    """φ = {2, 8} on the line 0..9, S = 0..6: the run must stay in S, so only φ ∩ S = {2} can be where it ends,
    and every cell of S reaches it (by hand); without S every cell wins."""
    K = 10
    game = build(integrators((K,)), "interleaved")
    phi = cells(game, 2, 8)
    S = cells(game, *range(7))
    for name, res in reach_and_stay(game, phi).items():
        assert members(game, res.domain, K) == list(range(10)), name
    results = reach_and_stay(game, phi, safe=S)
    for name, res in results.items():
        assert members(game, res.domain, K) == list(range(7)), name
    assert results["reach_safe"].details["safe_states"] == 1  # Safe(φ ∩ S) = {2}
    layered = reach_safe(game, phi, safe_set=S, layered=True)
    assert layered.domain == results["reach_safe"].domain and members(game, layered.layers[0], K) == [2]
    assert members(game, safe(game, S).domain, K) == list(range(7))  # the safe kind itself is unchanged


def test_reach_avoid_with_several_obstacle_boxes_on_a_plane():
    """A 10 x 10 plane, steps of one cell per axis, T the top right corner cell, two walls as obstacle boxes
    (Region.boxes, approximated from outside) with a gap each: the domain is what the explicit solver finds,
    meets no obstacle, and every run under the controller reaches T."""
    net = integrators((10, 10))
    ex = Explicit(net)
    game = build(net, "interleaved")
    g = UniformGrid.product([grid(10), grid(10)])
    walls = Region.model_validate({"boxes": [{"lb": [2.8, 0], "ub": [3.2, 7]}, {"lb": [6, 2.6], "ub": [6, 9]}]})
    A_region = abstract_region(walls, g, "avoid", outer=True)
    T_region = abstract_region(Region.model_validate({"boxes": [{"lb": [8.5, 8.5], "ub": [9.5, 9.5]}]}), g, "target")
    assert len(A_region.boxes) == 2 and A_region.states == 8 + 7
    bA, bT = region(game.model, A_region), region(game.model, T_region)
    points = np.array(ex.states)
    A, T = A_region.contains(points), T_region.contains(points)
    res = reach_avoid(game, bT, bA)
    dom = states_vector(game.model, res.domain, ex)
    np.testing.assert_array_equal(dom, ex.reach(T, A))
    assert not np.any(dom & A) and dom.sum() == 100 - 15  # every free cell goes round the walls
    check_progress(ex, controller_matrix(game.model, res.controller, ex), dom, T & ~A)
    # S = x >= 3 (the first wall's column and right of it): the 30 cells left of it go, the rest still go round.
    S = points[:, 0] >= 3
    res = reach_avoid(game, bT, bA, safe=state_set(game.model, points[S]))
    dom = states_vector(game.model, res.domain, ex)
    np.testing.assert_array_equal(dom, ex.reach(T, A | ~S))
    assert dom.sum() == 70 - 15  # x = 3..9 without the walls' cells


# ============================================================================ against the explicit solver
@pytest.mark.parametrize("shared", [True, False], ids=["shared_w", "per_subsystem_w"])
@pytest.mark.parametrize("seed", range(12))
def test_fixed_points_within_a_safe_set_match_the_explicit_solver(seed, shared):
    rng = np.random.default_rng(3100 + 100 * shared + seed)
    net = random_net(rng, shared)
    ex = Explicit(net)
    game = build(net, ["interleaved", "shared_top"][seed % 2])
    m = game.model
    S, T, A, phi = (random_set(rng, ex, p) for p in (0.75, 0.25, 0.1, 0.6))
    bS, bT, bA, bphi = (state_set(m, np.array(ex.states)[v]) for v in (S, T, A, phi))

    r = reach(game, bT, safe=bS)
    dom = states_vector(m, r.domain, ex)
    np.testing.assert_array_equal(dom, ex.reach(T, ~S))
    assert not np.any(dom & ~S)
    check_progress(ex, controller_matrix(m, r.controller, ex), dom, T & S)

    r = reach_avoid(game, bT, bA, safe=bS)
    dom = states_vector(m, r.domain, ex)
    np.testing.assert_array_equal(dom, ex.reach(T, A | ~S))
    check_progress(ex, controller_matrix(m, r.controller, ex), dom, T & S & ~A)
    assert reach_avoid(game, bT, bA, safe=bS, layered=True).domain == r.domain

    results = reach_and_stay(game, bphi, safe=bS)
    co, rs = results["cobuchi"], results["reach_safe"]
    dom_co, dom_rs = states_vector(m, co.domain, ex), states_vector(m, rs.domain, ex)
    np.testing.assert_array_equal(dom_co, ex.cobuchi(phi, S))
    np.testing.assert_array_equal(dom_rs, ex.reach(ex.safe(phi & S), ~S))
    assert not np.any(dom_rs & ~dom_co) and not np.any(dom_co & ~S)
    # Staying in the domain, which lies in S, is staying in S; no cycle outside φ: eventually in φ ∩ S.
    check_stay(ex, controller_matrix(m, co.controller, ex), dom_co, phi & S)
    check_stay(ex, controller_matrix(m, rs.controller, ex), dom_rs, phi & S)
    # Without S (S = everything) the results are the plain fixed points.
    everything = m.x_domain
    assert cobuchi(game, bphi, safe=everything).domain == cobuchi(game, bphi).domain
    assert reach(game, bT, safe=everything).domain == reach(game, bT).domain


@pytest.mark.parametrize("seed", range(4))
def test_layered_controllers_within_a_safe_set_equal_explicit_ones(seed):
    from pipelines.controller import controller_of

    rng = np.random.default_rng(4200 + seed)
    net = random_net(rng, bool(seed % 2))
    ex = Explicit(net)
    game = build(net, "interleaved")
    m = game.model
    S, T, phi = (state_set(m, np.array(ex.states)[random_set(rng, ex, p)]) for p in (0.75, 0.25, 0.6))
    meta = {"state_grid": UniformGrid.product([grid(k) for k in ex.shape]).describe(),
            "input_grids": [grid(k).describe() for k in net.n_u]}
    for solve in (lambda layered: reach(game, T, safe=S, layered=layered),
                  lambda layered: reach_safe(game, phi, safe_set=S, layered=layered)):
        explicit, layered = solve(False), solve(True)
        assert explicit.domain == layered.domain
        np.testing.assert_array_equal(layered_matrix(controller_of(game, layered, meta), ex),
                                      controller_matrix(m, explicit.controller, ex))


# ============================================================================ concrete closed loop
def _explicit(res) -> tuple[Explicit, dict[str, np.ndarray]]:
    """The explicit solver on a job's own abstraction, and its spec's regions as masks over its states."""
    from pipelines.spec.regions import spec_regions

    subs = res.network.subsystems
    net = Net([SubsystemLayout.of(s) for s in subs], res.relations, [g.size for g in res.network.internal_grids],
              list(res.interconnection.nodes), tuple(s.state_grid.size for s in subs),
              tuple(s.input_grid.size for s in subs))
    ex = Explicit(net)
    points = np.array(ex.states)
    masks = {k: r.contains(points) for k, r in spec_regions(res.spec, res.network).items()}
    return ex, masks


TOP_RIGHT = {"boxes": [{"lb": 6.5, "ub": 9.5}]}  # cells 7..9 on both axes
WALLS = {"boxes": [{"lb": [3, 0], "ub": [3, 3]}, {"lb": [6, 6], "ub": [6, 9]}]}  # x = 3, y 0..3; x = 6, y 6..9


@pytest.mark.parametrize("specification", [
    {"kind": "reach_avoid", "target": TOP_RIGHT, "avoid": WALLS},
    {"kind": "reach_avoid", "target": TOP_RIGHT, "avoid": WALLS, "safe": {"boxes": [{"lb": [0, 0.5], "ub": 9.5}]}},
    {"kind": "reach", "target": TOP_RIGHT, "safe": {"boxes": [{"lb": [2.5, 0], "ub": 9.5}]}},
    {"kind": "reach_and_stay", "target": {"boxes": [{"lb": 2.5, "ub": 5.5}]},
     "safe": {"boxes": [{"lb": [0, 1.5], "ub": 9.5}]}},
], ids=["two_obstacles", "two_obstacles_in_S", "reach_in_S", "stay_in_S"])
def test_closed_loop_runs_keep_the_safe_set_and_avoid_the_obstacles(specification):
    """The concrete integrators under the synthesized controllers: the domain is the explicit solver's on the same
    abstraction, lies in S and outside A, and no closed-loop run violates the specification; an initial state
    outside the domain (in a wall, or outside S) is named in the warnings."""
    from workers.control import run_synthesis
    from workers.job import run_abstraction

    outside = [3.0, 1.0] if "avoid" in specification else [8.0, 0.0] if specification["kind"] == "reach_and_stay" \
        else [0.0, 9.0]
    spec = parse_spec(integrator_spec(specification, initial_states=[[8.0, 8.0], outside]))
    res = run_abstraction(spec, audit=False)
    report = run_synthesis(res, None)
    ex, masks = _explicit(res)
    S = masks.get("safe", np.ones(ex.nX, bool))
    A = masks.get("avoid", np.zeros(ex.nX, bool))
    if spec.specification.kind == "reach_and_stay":
        want = {"cobuchi": ex.cobuchi(masks["target"], S),
                "reach_safe": ex.reach(ex.safe(masks["target"] & S), ~S)}
    else:
        want = {spec.specification.kind: ex.reach(masks["target"], A | ~S)}
    assert report["domain_states_by_fixed_point"] == {k: int(v.sum()) for k, v in want.items()}
    for v in want.values():
        assert 0 < v.sum() <= (S & ~A).sum() and not np.any(v & (A | ~S))
    closed = report["closed_loop"]
    assert closed["runs"] >= 30 and closed["violations"] == 0, closed["first_violation"]
    assert [rec["in_domain"] for rec in closed["initial_states"]] == [True, False]
    assert any(f"options.initial_states[1] = {outside}" in w for w in report["warnings"]), report["warnings"]


def test_a_safe_set_changes_the_domain_of_the_concrete_integrators():
    """The same target with and without S: S = x >= 2.5 removes the cells left of it, and no more (each of them
    reaches the target inside S)."""
    from workers.control import run_synthesis
    from workers.job import run_abstraction

    def domain(specification):
        return run_synthesis(run_abstraction(parse_spec(integrator_spec(specification, closed_loop_runs=0)),
                                             audit=False), None)["domain_states"]

    free = domain({"kind": "reach", "target": TOP_RIGHT})
    # The grid's end cells are [-0.5, 0.5] and [8.5, 9.5] (they meet the state box [0, 9]): S spans them whole.
    within = domain({"kind": "reach", "target": TOP_RIGHT, "safe": {"boxes": [{"lb": [2.5, -0.5], "ub": 9.5}]}})
    assert free == 100 and within == 70


def test_a_run_that_leaves_the_safe_set_is_a_violation_also_at_the_last_step():
    """The closed loop counts leaving S (or entering A) as a violation, also on a target cell and after the last
    step; a reach run that arrives in T inside S ends there."""
    from pipelines.network import build_network
    from pipelines.spec.regions import closed_loop_regions
    from pipelines.verification.closed_loop import simulate

    spec = parse_spec(integrator_spec({"kind": "reach", "target": TOP_RIGHT,
                                        "safe": {"boxes": [{"lb": [0, 2.5], "ub": 9.5}]}}))
    net = build_network(spec, None)
    regions = closed_loop_regions(spec, net)
    rng = np.random.default_rng(0)

    def push(dx, dy):
        return lambda x: np.array([[dx, dy]], dtype=float)

    down = simulate(net, push(0, -2), np.array([5.0, 4.0]), 5, rng, "reach", **regions)
    assert down.violation == "step 1: the state left the safe set" and down.states.shape[0] == 2
    last = simulate(net, push(0, -2), np.array([5.0, 4.0]), 1, rng, "reach", **regions)
    assert last.violation == "step 1: the state left the safe set"
    up = simulate(net, push(2, 2), np.array([4.0, 4.0]), 5, rng, "reach", **regions)
    assert up.violation is None and up.states.shape[0] == 3 and up.in_target[-1]  # (8, 8) after two steps
    walls = parse_spec(integrator_spec({"kind": "reach_avoid", "target": TOP_RIGHT, "avoid": WALLS}))
    into = simulate(net, push(1, 0), np.array([2.0, 1.0]), 3, rng, "reach_avoid", **closed_loop_regions(walls, net))
    assert into.violation == "step 1: the state entered the avoid set"


def test_an_empty_domain_is_said_in_the_warnings():
    """A target outside the safe set: nothing can win, the closed loop has no run, and the report says why and
    names the initial state outside the (empty) domain."""
    from workers.control import EMPTY_DOMAIN, run_synthesis
    from workers.job import run_abstraction

    specification = {"kind": "reach", "target": TOP_RIGHT, "safe": {"boxes": [{"lb": -1, "ub": 4.5}]}}
    spec = parse_spec(integrator_spec(specification, initial_states=[[1.0, 1.0]]))
    report = run_synthesis(run_abstraction(spec, audit=False), None)
    assert report["domain_states"] == 0 and report["closed_loop"]["runs"] == 0
    first, second, why = report["warnings"]
    assert first == EMPTY_DOMAIN.format(regions="target or safe set")
    assert first.startswith("the winning domain is empty: no controller exists on this abstraction")
    assert "options.initial_states[0] = [1.0, 1.0]" in second
    assert why.startswith("why the winning domain is empty: the target and the safe set share no whole cell")
