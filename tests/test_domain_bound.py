"""The outer bound of the reach-and-stay domain from upstream-closed groups (pipelines/synthesis/domain_bound.py).

Over random coupled networks the domain computed by the fixed points (and by the explicit solver) lies inside the
bound; on the tanks the bound rules the paper's initial state out in a fraction of a second at spacing 2.5, and
the synthesis report names it; at spacing 1.25 (tests/test_tanks_fine.py) it is what answers issue 24's question.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipelines.spec.model import load_spec
from pipelines.spec.regions import abstract_region
from pipelines.symbolic.relations import region, state_set
from pipelines.synthesis.cpre import ControllablePredecessor
from pipelines.synthesis.domain_bound import domain_bound, upstream_closed
from pipelines.synthesis.fixed_points import reach, reach_and_stay, safe
from workers.control import run_synthesis
from workers.job import run_abstraction

from .conftest import ROOT
from .games import Explicit, build, coupled_net, random_set, states_vector


def test_upstream_closed_groups_are_closures_smallest_first_without_the_whole_network():
    # 0 <- 1 <- 2, 3 reads 2 and 4, 4 reads 3 (a ring of two): closures {0}, {0,1}, {0,1,2}; {3,4,...} is all
    reads = {0: set(), 1: {0}, 2: {1}, 3: {2, 4}, 4: {3}}
    assert upstream_closed(reads) == [(0,), (0, 1), (0, 1, 2)]
    assert upstream_closed({0: {1}, 1: {0}}) == []  # everything reads everything: no group


def _random_game(seed: int):
    """A random coupled network (shared internal variables on odd seeds), its game and its explicit solver."""
    rng = np.random.default_rng(seed)
    shared = bool(seed % 2)
    net = coupled_net(rng, shared)
    game = build(net, ["interleaved", "shared_top"][seed % 2], "shared" if shared else "auto")
    return rng, game, Explicit(net)


def test_the_domain_lies_inside_the_bound_on_random_networks():
    """Over 40 random coupled networks (sources, chains, trees, rings; some internal variables shared): the
    reach-and-stay domain, which the explicit solver gives, lies inside the bound; some bound cuts states off
    (else nothing here would test the games)."""
    cut = grouped = 0
    for seed in range(40):
        rng, game, ex = _random_game(9100 + seed)
        m = game.model
        phi = random_set(rng, ex, 0.75)
        bphi = state_set(m, np.array(ex.states)[phi])
        domain = reach_and_stay(game, bphi, ("reach_safe",))["reach_safe"].domain
        np.testing.assert_array_equal(states_vector(m, domain, ex), ex.reach(ex.safe(phi)))
        bound = domain_bound(game, "reach_and_stay", bphi)
        assert domain & ~bound.bound == game.bdd.false, f"seed {seed}: the bound cut off a domain state"
        grouped += bool(bound.groups)
        cut += (m.x_domain & ~bound.bound) != game.bdd.false
    assert grouped >= 10 and cut >= 5, (grouped, cut)


def test_the_other_kinds_domains_lie_inside_their_bounds_on_random_networks():
    """Safety, reachability inside a safe set and reach-avoid over 30 random coupled networks: each domain, which
    the explicit solver gives, lies inside its bound; some bounds cut states off."""
    cut = {"safe": 0, "reach": 0, "reach_avoid": 0}
    for seed in range(30):
        rng, game, ex = _random_game(9300 + seed)
        m = game.model
        S, T, A = random_set(rng, ex, 0.85), random_set(rng, ex, 0.3), random_set(rng, ex, 0.1)
        bS, bT, bA = (state_set(m, np.array(ex.states)[v]) for v in (S, T, A))
        cases = {
            "safe": (safe(game, bS).domain, ex.safe(S), domain_bound(game, "safe", bS)),
            "reach": (reach(game, bT, safe=bS).domain, ex.reach(T, ~S), domain_bound(game, "reach", bT, safe=bS)),
            "reach_avoid": (reach(game, bT, bA).domain, ex.reach(T, A),
                            domain_bound(game, "reach_avoid", bT, avoid=bA)),
        }
        for kind, (domain, explicit, bound) in cases.items():
            np.testing.assert_array_equal(states_vector(m, domain, ex), explicit)
            assert domain & ~bound.bound == game.bdd.false, f"seed {seed}, {kind}: the bound cut off a domain state"
            cut[kind] += (m.x_domain & ~bound.bound) != game.bdd.false
    assert min(cut.values()) >= 3, cut
    with pytest.raises(ValueError, match="no domain bound"):
        domain_bound(game, "cobuchi", bT)


@pytest.fixture(scope="module")
def tanks():
    return run_abstraction(load_spec(ROOT / "examples" / "tanks.yaml"), audit=False)


def test_on_the_tanks_the_domain_is_inside_and_the_papers_initial_state_outside(tanks):
    net, spec = tanks.network, tanks.spec
    cpre = ControllablePredecessor.from_network(net, tanks.relations, tanks.interconnection)
    try:
        m = cpre.model
        grid = net.composed_state_grid()
        T = region(m, abstract_region(spec.specification.target, grid, "target"))
        bound = domain_bound(cpre, "reach_and_stay", T)
        # the cascade's closures: tanks 1, 4, 1-2, 4-5, 1-3, 4-5-7, 1-3-8 (tanks 1-7 has 42 bits: left out)
        assert bound.groups == [(0,), (3,), (0, 1), (3, 4), (0, 1, 2), (3, 4, 6), (0, 1, 2, 7)]
        domain = reach_and_stay(cpre, T, ("reach_safe",))["reach_safe"].domain
        assert domain != m.bdd.false and domain & ~bound.bound == m.bdd.false
        idx, _ = grid.cell_of(np.array(spec.options.initial_states))
        assert bound.ruled_out_by(state_set(m, idx)) == (0, 1)  # tanks 1 and 2 cannot win from (5, 6)
        inside = m.bdd.cube(m.bdd.pick(domain, care_vars=set(m.x_bits)))  # one state of the domain
        assert (inside & ~domain) == m.bdd.false and bound.ruled_out_by(inside) is None
    finally:
        cpre.close()


def test_the_synthesis_report_names_the_initial_states_the_bound_rules_out(tanks, tmp_path):
    lines: list[str] = []
    report = run_synthesis(tanks, tmp_path, runs=5, progress=lambda stage, done, total, text="": lines.append(text))
    bound = report["synthesis"]["domain_bound"]
    assert bound["initial_states_outside"] == [{"index": 0, "group": ["tank1", "tank2"]}]
    assert bound["groups"][0] == ["tank1"]
    # the bound's states: more than the domain has (the local groups leave tanks 9 and 10 free), fewer than all
    assert report["domain_states"] < bound["domain_states_at_most"] < tanks.report["abstract_states"]
    assert any(t.startswith("domain bound: initial state 0 is outside the domain (the game of tank1, tank2")
               for t in lines)
    assert report["closed_loop"]["initial_states"][0]["in_domain"] is False  # what the fixed point then found
