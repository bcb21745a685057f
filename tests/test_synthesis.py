"""Symbolic fixed points (docs/method.md §6) against an explicit-state solver on small random networks.

Each random network has 2-3 subsystems with 3-6 states and 2 inputs, and either one internal variable shared
by all subsystems (a random node relation x -> w, sometimes through an intermediate z) or one internal variable
per subsystem (the tanks' structure). The explicit solver enumerates composed states, joint inputs and every
``ŵ ∈ M̂(x̂)``; it shares no code with the symbolic one beyond the input arrays.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from pipelines.abstraction.relation import SubsystemRelation
from pipelines.grid import UniformGrid
from pipelines.interconnection import NodeRelation
from pipelines.spec.model import load_spec
from pipelines.spec.regions import abstract_region
from pipelines.symbolic.counting import inputs_at
from pipelines.symbolic.order import SubsystemLayout
from pipelines.symbolic.relations import interconnection_parts, state_set, subsystem_relations
from pipelines.symbolic.symbolic_model import SymbolicModel
from pipelines.synthesis.cpre import CHAIN_ORDERS, ControllablePredecessor, predecessors_of
from pipelines.synthesis.fixed_points import reach, reach_and_stay, reach_avoid, safe
from pipelines.synthesis.options import SynthesisOptions
from pipelines.synthesis.synthesize import synthesize
from workers.job import run_abstraction

from .conftest import EXAMPLES
from .games import (
    Explicit,
    Net,
    build,
    check_progress,
    check_stay,
    controller_matrix,
    layered_matrix,
    random_net,
    random_set,
    ring_net,
    states_vector,
)
from .strategies import grid

SEEDS = list(range(40))


@pytest.mark.parametrize("shared", [True, False], ids=["shared_w", "per_subsystem_w"])
@pytest.mark.parametrize("seed", SEEDS)
def test_fixed_points_match_the_explicit_solver(seed, shared):
    rng = np.random.default_rng(1000 * shared + seed)
    net = random_net(rng, shared)
    ex = Explicit(net)
    order = ["interleaved", "shared_top"][seed % 2]
    game = build(net, order)
    assert game.method == ("shared" if shared else "per_subsystem")
    m = game.model

    S, T, A, phi = (random_set(rng, ex, p) for p in (0.8, 0.2, 0.15, 0.6))
    bS, bT, bA, bphi = (state_set(m, np.array(ex.states)[v]) for v in (S, T, A, phi))

    # CPre itself on a random set
    Z = random_set(rng, ex, 0.6)
    np.testing.assert_array_equal(controller_matrix(m, game.cpre(state_set(m, np.array(ex.states)[Z])), ex),
                                  ex.cpre(Z))

    r = safe(game, bS)
    dom = states_vector(m, r.domain, ex)
    np.testing.assert_array_equal(dom, ex.safe(S))
    assert r.domain_states == dom.sum()
    C = controller_matrix(m, r.controller, ex)
    np.testing.assert_array_equal(C, ex.cpre(dom) & dom[:, None])  # every input keeping the invariant

    r = reach(game, bT)
    dom = states_vector(m, r.domain, ex)
    np.testing.assert_array_equal(dom, ex.reach(T))
    check_progress(ex, controller_matrix(m, r.controller, ex), dom, T)

    r = reach_avoid(game, bT, bA)
    dom = states_vector(m, r.domain, ex)
    np.testing.assert_array_equal(dom, ex.reach(T, A))
    assert not np.any(dom & A)
    check_progress(ex, controller_matrix(m, r.controller, ex), dom, T & ~A)

    results = reach_and_stay(game, bphi)
    co, rs = results["cobuchi"], results["reach_safe"]
    dom_co, dom_rs = states_vector(m, co.domain, ex), states_vector(m, rs.domain, ex)
    np.testing.assert_array_equal(dom_co, ex.cobuchi(phi))
    np.testing.assert_array_equal(dom_rs, ex.reach(ex.safe(phi)))
    assert not np.any(dom_rs & ~dom_co)  # Reach(Safe(φ)) ⊆ co-Büchi winning set
    assert rs.details["safe_states"] == ex.safe(phi).sum()
    check_stay(ex, controller_matrix(m, co.controller, ex), dom_co, phi)
    check_stay(ex, controller_matrix(m, rs.controller, ex), dom_rs, phi)
    for res in (co, rs):
        assert res.domain_states == states_vector(m, res.domain, ex).sum()
        assert res.iterations >= 1 and res.seconds >= 0 and res.peak_nodes > 0


@pytest.mark.parametrize("seed", range(10))
def test_shared_cpre_equals_per_subsystem_cpre_where_both_apply(seed):
    """Both CPre implementations are exact, so on per-subsystem networks they must agree, in every
    conjunction schedule; ``predecessors`` is ``∃u.CPre``."""
    rng = np.random.default_rng(500 + seed)
    net = random_net(rng, shared=False)
    ex = Explicit(net)
    games = [build(net, "interleaved", method, chain) for method in ("per_subsystem", "shared")
             for chain in CHAIN_ORDERS]
    for _ in range(5):
        Z = random_set(rng, ex, 0.6)
        for g in games:
            bZ = state_set(g.model, np.array(ex.states)[Z])
            C = controller_matrix(g.model, g.cpre(bZ), ex)
            np.testing.assert_array_equal(C, ex.cpre(Z))
            np.testing.assert_array_equal(states_vector(g.model, g.predecessors(bZ), ex), C.any(axis=1))


@pytest.mark.parametrize("seed", range(8))
def test_cpre_within_a_set_is_exact_there_and_empty_elsewhere(seed):
    """``ControllablePredecessor.within(S)`` restricts the relations to the projections of ``S``: CPre and the predecessors are
    then ``CPre ∧ S`` exactly, for every ``Z`` (not only ``Z ⊆ S``), in both CPre methods."""
    rng = np.random.default_rng(900 + seed)
    shared = bool(seed % 2)
    net = random_net(rng, shared)
    ex = Explicit(net)
    game = build(net, ["interleaved", "shared_top"][seed % 4 // 2])
    m = game.model
    for _ in range(4):
        S, Z = random_set(rng, ex, 0.7), random_set(rng, ex, 0.6)
        bS, bZ = (state_set(m, np.array(ex.states)[v]) for v in (S, Z))
        inside = game.within(bS)
        C = controller_matrix(m, game.cpre(bZ, inside), ex)
        np.testing.assert_array_equal(C, ex.cpre(Z) & S[:, None])
        np.testing.assert_array_equal(states_vector(m, game.predecessors(bZ, within=inside), ex),
                                      ex.cpre(Z).any(axis=1) & S)


@pytest.mark.parametrize("seed", range(8))
def test_predecessors_on_states_and_parts_are_exact_there(seed):
    """:func:`predecessors_of` with ``states`` (taken at the ``∃w`` step, not in the chain) and ``part`` (in the
    chain too), alone and together, with and without ``outside``: ``∃u.CPre`` on their intersection, exactly,
    against the explicit solver, in both CPre methods."""
    rng = np.random.default_rng(1300 + seed)
    shared = bool(seed % 2)
    net = random_net(rng, shared)
    ex = Explicit(net)
    for method in (("shared",) if shared else ("per_subsystem", "shared")):
        game = build(net, ["interleaved", "shared_top"][seed % 4 // 2], method)
        m = game.model
        for _ in range(3):
            S, P, Z = random_set(rng, ex, 0.5), random_set(rng, ex, 0.7), random_set(rng, ex, 0.6)
            bS, bP, bZ = (state_set(m, np.array(ex.states)[v]) for v in (S, P, Z))
            want = ex.cpre(Z).any(axis=1)
            for part, states, mask in ((None, bS, S), (bP, bS, S & P), (bP, None, P)):
                for outside, where in ((None, mask), (~bZ, mask & ~Z)):
                    got = predecessors_of(m, game.chain, game.admissible, game.M, game.w_bits, game.u_bits, bZ,
                                          outside, part, states)
                    vec = states_vector(m, got, ex)
                    np.testing.assert_array_equal(vec & where, want & where)
                    assert not np.any(vec & ~mask), "an answer outside part and states"
            np.testing.assert_array_equal(states_vector(m, game.predecessors(bZ, part=bP, states=bS), ex), want & S & P)
            with pytest.raises(ValueError, match="with a part only"):
                game.predecessors(bZ, states=bS)


def test_per_subsystem_method_is_refused_for_a_shared_internal_variable():
    net = random_net(np.random.default_rng(1), shared=True)
    with pytest.raises(ValueError, match="read by at most one subsystem"):
        build(net, "shared_top", "per_subsystem")


def test_blocking_for_one_admissible_w_makes_the_input_inadmissible():
    """docs/method.md §6: with w quantified per subsystem, an input that blocks for one w ∈ M̂(x) must not count."""
    lay = [SubsystemLayout(0, (2,), 2, (0,), "a", 0)]
    lo = np.zeros((2, 2, 2, 1), np.int32)
    hi = np.ones((2, 2, 2, 1), np.int32)
    blocking = np.zeros((2, 2, 2), bool)
    blocking[0, 0, 1] = True  # input 0 at x=0 blocks under w=1 only
    lo[0, 0, 1], hi[0, 0, 1] = 0, -1
    rel = SubsystemRelation("t", lo, hi, blocking, 1, 1)
    node = NodeRelation("w0", grid(2), ("x0",), (grid(2),), None, np.array([0, 0], np.int32),
                        np.array([1, 0], np.int32), 0.0)  # M̂(x=0) = {0, 1}, M̂(x=1) = {0}
    m = SymbolicModel(lay, [2], order="interleaved")
    T, NB = subsystem_relations(m, {"a": rel})
    game = ControllablePredecessor(m, T, NB, interconnection_parts(m, [node]))
    C = game.cpre(m.x_domain)
    np.testing.assert_array_equal(inputs_at(m, C, [0]), [[1]])
    np.testing.assert_array_equal(inputs_at(m, C, [1]), [[0], [1]])


def test_small_example_end_to_end_against_the_explicit_solver():
    """examples/small.yaml (2 consensus agents, shared w): the real relations and interconnection, solved
    symbolically (both orders) and explicitly; both reach-and-stay fixed points and their controllers."""
    res = run_abstraction(load_spec(EXAMPLES / "small.yaml"), audit=False)
    subs = res.network.subsystems
    net = Net([SubsystemLayout.of(s) for s in subs], res.relations, [g.size for g in res.network.internal_grids],
              list(res.interconnection.nodes), tuple(s.state_grid.size for s in subs),
              tuple(s.input_grid.size for s in subs))
    ex = Explicit(net)
    region = abstract_region(res.spec.specification.target, res.network.composed_state_grid(), "target")
    phi = region.contains(np.array(ex.states))
    expected = ex.cobuchi(phi)
    assert expected.sum() > phi.sum() // 2  # a non-trivial domain
    np.testing.assert_array_equal(ex.reach(ex.safe(phi)), expected)  # as docs/method.md §6 found for consensus
    from pipelines.controller import controller_of

    meta = {"state_grid": res.network.composed_state_grid().describe(),
            "input_grids": [s.input_grid.describe() for s in subs]}
    for order, form, method in (("shared_top", "auto", "auto"), ("interleaved", "explicit", "auto"),
                                ("interleaved", "auto", "chained")):
        game, results, report = synthesize(res.network, res.relations, res.interconnection, res.spec.specification,
                                           SynthesisOptions(order=order, controller_form=form, method=method))
        assert game.method == ("shared" if method == "auto" else method) and report["order"] == order
        for name, r in results.items():
            dom = states_vector(game.model, r.domain, ex)
            np.testing.assert_array_equal(dom, expected, err_msg=name)
            assert r.domain_states == report["results"][name]["domain_states"] == int(expected.sum())
            # auto = layered for a shared-w CPre (the co-Büchi controller is always explicit)
            assert bool(r.layers) == (form == "auto" and name == "reach_safe")
            C = layered_matrix(controller_of(game, r, meta), ex) if r.layers else \
                controller_matrix(game.model, r.controller, ex)
            check_stay(ex, C, dom, phi)


@pytest.mark.parametrize("shared", [True, False], ids=["shared_w", "per_subsystem_w"])
def test_cpre_at_a_state_is_cpre_cofactored_there(shared):
    """``ControllablePredecessor.cpre_at`` (the layered controllers' one-state CPre, with ¬Z' cut to the reachable next cells) is
    ``CPre(Z)`` at that state, for every state and several sets."""
    rng = np.random.default_rng(90 + shared)
    net = random_net(rng, shared)
    ex = Explicit(net)
    game = build(net, "shared_top" if shared else "interleaved")
    m = game.model
    for p in (0.3, 0.6, 0.9):
        bZ = state_set(m, np.array(ex.states)[random_set(rng, ex, p)])
        whole, Zn = game.cpre(bZ), m.to_next(bZ)
        for s in ex.states:
            state = m.state_assignment(list(s))
            assert game.cpre_at(state, Zn) == m.bdd.let(state, whole), (p, s)
    # the chain's cofactors are kept across the calls (and sets), and dropped with the game's close
    assert game._at is not None and all(game._at._kept)
    game.close()
    assert game._at is None
    state = m.state_assignment(list(ex.states[0]))
    assert game.cpre_at(state, Zn) == m.bdd.let(state, whole)


@pytest.mark.parametrize("shared", [True, False], ids=["shared_w", "per_subsystem_w"])
def test_the_chains_cofactors_kept_across_states_give_cpre_at_each_state(shared):
    """``ChainAtStates`` (what a layered controller keeps across the cells of a closed loop) gives ``CPre(Z)`` at every
    state, for several sets, the same as computing the cofactors afresh, and keeps each relation's cofactors by its
    own subsystem's state: fewer than the composed states where a relation reads part of the state (the shared-``w``
    chain's ``T_i``; per subsystem, ``∃w_i. M̂_i ∧ T_i`` reads the subsystems ``w_i`` comes from, here all)."""
    from pipelines.synthesis.at_state import ChainAtStates, cpre_at_state

    rng = np.random.default_rng(190 + shared)
    net = random_net(rng, shared)
    ex = Explicit(net)
    game = build(net, "shared_top" if shared else "interleaved")
    m = game.model
    at = ChainAtStates(m, game.chain)
    for p in (0.3, 0.6, 0.9):
        bZ = state_set(m, np.array(ex.states)[random_set(rng, ex, p)])
        whole, Zn = game.cpre(bZ), m.to_next(bZ)
        for s in ex.states:
            state = m.state_assignment(list(s))
            kept = cpre_at_state(m, game.chain, game.admissible, game.M, state, Zn, at)
            assert kept == cpre_at_state(m, game.chain, game.admissible, game.M, state, Zn) == m.bdd.let(state, whole)
    partial = [i for i, reads in enumerate(at._reads) if len(reads) < len(m.x_bits)]
    assert partial or not shared, "every relation reads the whole state: the test would not exercise the keeping"
    for i in partial:
        assert len(at._kept[i]) < len(ex.states)


# ============================================================================ layered controllers


@pytest.mark.parametrize("shared", [True, False], ids=["shared_w", "per_subsystem_w"])
@pytest.mark.parametrize("seed", SEEDS[:6])
def test_layered_controllers_equal_explicit_ones_cell_for_cell(seed, shared, tmp_path):
    from pipelines.controller import LayeredController, controller_of
    from pipelines.controller_loading import load_controller

    rng = np.random.default_rng(7000 + 1000 * shared + seed)
    net = random_net(rng, shared)
    ex = Explicit(net)
    game = build(net, ["interleaved", "shared_top"][seed % 2])
    m = game.model
    S, T, A, phi = (state_set(m, np.array(ex.states)[random_set(rng, ex, p)]) for p in (0.8, 0.2, 0.15, 0.6))
    meta = {"state_grid": UniformGrid.product([grid(k) for k in ex.shape]).describe(),
            "input_grids": [grid(k).describe() for k in net.n_u]}
    cases = {
        "safe": lambda layered: safe(game, S, layered=layered),
        "reach": lambda layered: reach(game, T, layered=layered),
        "reach_avoid": lambda layered: reach_avoid(game, T, A, layered=layered),
        "reach_safe": lambda layered: reach_and_stay(game, phi, ("reach_safe",), layered=layered)["reach_safe"],
    }
    for name, solve in cases.items():
        explicit, layered = solve(False), solve(True)
        assert explicit.domain == layered.domain, name
        assert layered.controller is None and layered.layers[-1] == layered.domain
        ctrl = controller_of(game, layered, meta)
        assert isinstance(ctrl, LayeredController)
        want = controller_matrix(m, explicit.controller, ex)
        np.testing.assert_array_equal(layered_matrix(ctrl, ex), want, err_msg=name)
        np.testing.assert_array_equal(layered_matrix(ctrl, ex), want, err_msg=f"{name}, cached input sets")
        for xf in rng.choice(ex.nX, size=min(ex.nX, 8), replace=False):  # one input drawn = one of the listed
            x = np.array(ex.states[xf], dtype=float)
            drawn, first = ctrl.choose(x, rng), ctrl.choose(x, rng, "first")
            if not want[xf].any():
                assert drawn is None and first is None
                continue
            listed = ctrl.inputs(x)
            assert any(np.array_equal(drawn, row) for row in listed)
            np.testing.assert_array_equal(first, listed[0])
        ctrl.save(tmp_path, name)
        back = load_controller(tmp_path, name)
        assert isinstance(back, LayeredController)
        np.testing.assert_array_equal(layered_matrix(back, ex), want, err_msg=f"{name} after save/load")


@pytest.mark.parametrize("seed", range(6))
def test_greedy_schedule_is_the_greedy_rule(seed):
    """The incremental greedy order (:func:`schedule`) is the rule's order computed from its definition
    (``_greedy_plain``), on random chains shaped like a CPre's: each relation reads a few current-state and
    shared bits and owns its next-state bits."""
    from dd.cudd import BDD

    from pipelines.synthesis.schedule import _greedy_plain, schedule

    rng = np.random.default_rng(900 + seed)
    bdd = BDD()
    n_rel = int(rng.integers(2, 40))
    current = [f"x{k}" for k in range(int(rng.integers(3, 30)))]
    nxt = [[f"xn{k}_{b}" for b in range(int(rng.integers(1, 4)))] for k in range(n_rel)]
    bdd.declare(*current, *itertools.chain.from_iterable(nxt))
    chain = []
    for k in range(n_rel):
        reads = rng.choice(current, size=int(rng.integers(1, min(6, len(current)) + 1)), replace=False)
        rel = bdd.true
        for v in [*reads, *nxt[k]]:
            rel &= bdd.var(str(v))
        chain.append((rel, nxt[k]))
    start = set(itertools.chain.from_iterable(nxt))
    supports = [set(bdd.support(r)) for r, _ in chain]
    want = _greedy_plain(chain, supports, [set(x) for _, x in chain], set(start))
    got = schedule(chain, start, bdd, "greedy")
    assert [x for _, x in got] == [x for _, x in want]
    del chain, got, want


@pytest.mark.parametrize("seed", range(12))
def test_chained_cpre_matches_the_explicit_solver(seed):
    """The chained CPre (each part of M̂ a link of the chain, ŵ_j quantified after its last reader) is exact: on rings
    whose internal variables are each read by two subsystems (the rooms' structure), and on both kinds of random
    network, in every conjunction schedule; so is the shared one on the rings."""
    rng = np.random.default_rng(3000 + seed)
    net = [ring_net(rng), random_net(rng, True), random_net(rng, False)][seed % 3]
    ex = Explicit(net)
    order = ["interleaved", "shared_top"][seed // 3 % 2]
    games = [build(net, order, "chained", chain) for chain in CHAIN_ORDERS]
    if seed % 3 == 0:
        games.append(build(net, order, "shared"))
    S, T, phi = (random_set(rng, ex, p) for p in (0.8, 0.2, 0.6))
    for g in games:
        m = g.model
        for _ in range(3):
            Z = random_set(rng, ex, 0.6)
            bZ = state_set(m, np.array(ex.states)[Z])
            C = controller_matrix(m, g.cpre(bZ), ex)
            np.testing.assert_array_equal(C, ex.cpre(Z))
            np.testing.assert_array_equal(states_vector(m, g.predecessors(bZ), ex), C.any(axis=1))
        bS, bT, bphi = (state_set(m, np.array(ex.states)[v]) for v in (S, T, phi))
        np.testing.assert_array_equal(states_vector(m, safe(g, bS).domain, ex), ex.safe(S))
        r = reach(g, bT)
        dom = states_vector(m, r.domain, ex)
        np.testing.assert_array_equal(dom, ex.reach(T))
        check_progress(ex, controller_matrix(m, r.controller, ex), dom, T)
        rs = reach_and_stay(g, bphi, methods=("reach_safe",))["reach_safe"]
        np.testing.assert_array_equal(states_vector(m, rs.domain, ex), ex.reach(ex.safe(phi)))


@pytest.mark.parametrize("seed", range(12))
def test_per_reader_cpre_is_sound_and_exact_where_each_variable_has_one_reader(seed):
    """The per-reader CPre lets every reader of a shared ŵ see its own value: it gives the environment more choices,
    so its CPre and domains lie inside the exact ones and its controllers win the exact game; with one reader per
    variable it is the per-subsystem CPre, exact."""
    rng = np.random.default_rng(4000 + seed)
    net = [ring_net(rng), random_net(rng, True), random_net(rng, False)][seed % 3]
    ex = Explicit(net)
    g = build(net, ["interleaved", "shared_top"][seed // 3 % 2], "per_reader")
    m = g.model
    exact = seed % 3 == 2
    S, T = random_set(rng, ex, 0.8), random_set(rng, ex, 0.2)
    for _ in range(3):
        Z = random_set(rng, ex, 0.6)
        C = controller_matrix(m, g.cpre(state_set(m, np.array(ex.states)[Z])), ex)
        assert not np.any(C & ~ex.cpre(Z))
        if exact:
            np.testing.assert_array_equal(C, ex.cpre(Z))
    r = safe(g, state_set(m, np.array(ex.states)[S]))
    dom = states_vector(m, r.domain, ex)
    assert not np.any(dom & ~ex.safe(S))
    C = controller_matrix(m, r.controller, ex)
    assert not np.any(C & ~ex.cpre(dom))  # every input it allows keeps the exact game in its domain
    assert np.all(C.any(axis=1)[dom])
    r = reach(g, state_set(m, np.array(ex.states)[T]))
    dom = states_vector(m, r.domain, ex)
    assert not np.any(dom & ~ex.reach(T))
    check_progress(ex, controller_matrix(m, r.controller, ex), dom, T)
    if exact:
        np.testing.assert_array_equal(dom, ex.reach(T))
