"""Interchangeable subsystems (pipelines/synthesis/symmetry.py): found only where every CPre ingredient is invariant,
and ``∃u.CPre`` computed on one state per orbit and closed is the plain one, in one process and on the cluster."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from pipelines.spec.model import parse_spec
from pipelines.spec.regions import abstract_region
from pipelines.symbolic.relations import region
from pipelines.synthesis.cpre import ControllablePredecessor
from pipelines.synthesis.fixed_points import reach, reach_safe, safe
from pipelines.synthesis.symmetry import find_symmetry
from tests.games import build, random_net
from workers.dask_cpre import DaskPredecessors, on_cluster
from workers.job import run_abstraction
from workers.processes.partitioned_cpre import PartitionedPredecessors

from .conftest import EXAMPLES


def _consensus(N: int, order: str | None = None, symmetry: bool = True):
    """The consensus example at N agents: its CPre (one process) and its target ``φ``."""
    data = yaml.safe_load((EXAMPLES / "consensus.yaml").read_text())
    data["parameters"]["N"] = N
    data["options"]["initial_states"] = []
    spec = parse_spec(yaml.safe_dump(data))
    a = run_abstraction(spec, audit=False)
    game = ControllablePredecessor.from_network(a.network, a.relations, a.interconnection, order=order,
                                                processes=1)
    game.use_symmetry = symmetry
    grid = a.network.composed_state_grid()
    return game, region(game.model, abstract_region(spec.specification.target, grid, "target"))


@pytest.fixture(scope="module")
def consensus3():
    return _consensus(3)


def _random_set(game, rng, p: float):
    """A random set of states (each code of each digit kept with probability p, then a random union of boxes)."""
    m, bdd = game.model, game.bdd
    f = bdd.false
    for _ in range(4):
        box = bdd.true
        for d in m.x_digits():
            lo = int(rng.integers(0, m.sizes[d]))
            hi = int(rng.integers(lo, m.sizes[d]))
            box &= m.interval(d, lo, hi)
        f |= box
    return f & m.x_domain


def test_the_consensus_agents_are_interchangeable(consensus3):
    game, _ = consensus3
    sym = game.symmetry
    assert sym is not None and sym.classes == [[0, 1, 2]]
    assert sym.invariant(game.M) and sym.invariant(game.admissible)
    R = sym.representatives
    assert sym.close(R) == game.model.x_domain  # one state of every orbit of the grid's cells
    assert not sym.invariant(R)


def test_a_swap_that_changes_the_interconnection_is_refused():
    """Random shared networks: a pair is accepted only if the swap fixes M̂, the admissible pairs and the chain."""
    for seed in range(40):
        game = build(random_net(np.random.default_rng(seed), True), "shared_top")
        m = game.model
        found = find_symmetry(m, game.chain, game.M, game.admissible)
        if found is None:
            continue
        for s in found.swaps:
            assert m.bdd.let(s, game.M) == game.M and m.bdd.let(s, game.admissible) == game.admissible
    # nothing here forces a symmetric random M̂: the test only checks what was accepted


@pytest.mark.parametrize("seed", range(3))
def test_predecessors_on_representatives_equal_the_plain_ones(consensus3, seed):
    """Invariant sets (closed random sets): whole, ``outside`` and ``within``; a set that is not invariant falls
    back to the plain computation. Each against the same call with the symmetry off."""
    game, _ = consensus3
    sym = game.symmetry
    rng = np.random.default_rng(seed)

    def both(*args, **kw):
        game.use_symmetry, game._symmetry = False, False
        plain = game.predecessors(*args, **kw)
        game.use_symmetry, game._symmetry = True, False
        return game.predecessors(*args, **kw), plain

    for _ in range(3):
        Z = sym.close(_random_set(game, rng, 0.5))
        S = sym.close(_random_set(game, rng, 0.5))
        got, want = both(Z)
        assert got == want
        got, want = both(Z, outside=~Z)
        assert got & ~Z == want & ~Z
        inside = game.within(S)
        got, want = both(Z, within=inside)
        assert got == want
        skew = _random_set(game, rng, 0.5)
        if not sym.invariant(skew):
            assert game._symmetry_for(skew, None, None) is None
            got, want = both(skew)
            assert got == want
            # an invariant Z with an outside that is not (only ¬Z is taken as invariant without a check)
            assert game._symmetry_for(Z, skew, None) is None and game._symmetry_for(Z, ~Z, None) is not None
            got, want = both(Z, outside=skew)
            assert got & skew == want & skew


def test_fixed_points_give_the_same_domains_with_and_without_symmetry(consensus3):
    game, phi = consensus3
    out = {}
    for on in (True, False):
        game.use_symmetry, game._symmetry = on, False
        out[on] = (safe(game, phi, layered=True).domain, reach(game, phi, layered=True).domain,
                   reach_safe(game, phi, layered=True).domain)
    assert out[True] == out[False]
    assert out[True][2] != game.bdd.false


def test_iterates_combined_from_invariant_sets_are_recognised_and_nothing_else_is(consensus3, monkeypatch):
    """``InvariantSets``: after a call on ``Z`` answered ``P`` (closed), ``Z ∧ P`` and ``Z ∨ (P ∧ K)`` for a
    ``within`` set ``K`` are taken as invariant without a check; the same shapes from a ``K`` that is not
    invariant, and other sets, are checked (and refused where they are not). A Reach(Safe) checks far fewer sets
    than it has iterations and gives the domain of the plain CPre."""
    from pipelines.synthesis.symmetry import InvariantSets, Symmetry

    game, phi = consensus3
    game.use_symmetry, game._symmetry = True, False
    sym = game.symmetry
    checked: list[int] = []
    invariant = Symmetry.invariant

    def counting(self, f):
        checked.append(1)
        return invariant(self, f)

    monkeypatch.setattr(Symmetry, "invariant", counting)
    rng = np.random.default_rng(7)
    Z, P, K = (sym.close(_random_set(game, rng, 0.5)) for _ in range(3))
    while len({Z, P, K, Z & P, Z | (P & K), Z | P}) < 6:  # each shape its own set: none recognised by another
        Z, P, K = (sym.close(_random_set(game, rng, 0.5)) for _ in range(3))
    skew = _random_set(game, rng, 0.5)
    while invariant(sym, skew) or invariant(sym, Z | (P & skew)):
        skew = _random_set(game, rng, 0.5)
    known = InvariantSets()
    known.may_join(K)
    known.may_join(skew)
    known.step(sym, Z, P)
    checked.clear()
    assert known.holds(sym, Z & P) and known.holds(sym, Z | (P & K)) and known.holds(sym, P)
    recognised = len(checked)
    assert recognised == 2  # the two within() sets, once each; the iterates themselves not
    assert not known.holds(sym, Z | (P & skew)) and len(checked) == recognised + 1
    assert not known.holds(sym, skew)
    other = Symmetry(game.model, sym.classes)  # another symmetry object: what was known of sym is not taken
    checked.clear()
    assert known.holds(other, Z & P) and len(checked) == 1
    known.forget()
    assert known.holds(sym, Z & P) and len(checked) == 2

    checked.clear()
    with_sym = reach_safe(game, phi, layered=True)
    assert 0 < len(checked) < with_sym.iterations
    game.use_symmetry, game._symmetry = False, False
    try:
        assert reach_safe(game, phi, layered=True).domain == with_sym.domain
    finally:
        game.use_symmetry, game._symmetry = True, False


@pytest.mark.parametrize("cut", ["window", "x", "processes"])
def test_parts_close_their_representatives(consensus3, client, cut):
    """Each part (on a worker, or in a helper process) computes its states' representatives and closes its own
    answer: the union is the plain ``∃u.CPre`` (whole, ``outside``, ``within``) at random cuts."""
    game, _ = consensus3
    game.use_symmetry, game._symmetry = True, False
    sym = game.symmetry
    rng = np.random.default_rng(40 + len(cut))
    pool = PartitionedPredecessors(game, 3) if cut == "processes" else DaskPredecessors(game, 3, client=client, cut=cut)
    try:
        assert pool.takes_symmetry
        for k in range(3):
            if k:
                pool.cuts = sorted(rng.choice(np.arange(1, pool.cells), size=len(pool.cuts), replace=False).tolist())
            Z = sym.close(_random_set(game, rng, 0.5))
            S = sym.close(_random_set(game, rng, 0.5))
            game.use_symmetry, game._symmetry = False, False
            want, want_out, want_in = (game.predecessors(Z), game.predecessors(Z, outside=~Z),
                                       game.predecessors(Z, within=game.within(S)))
            game.use_symmetry, game._symmetry = True, False
            assert pool(Z, None, None, sym) == want
            assert pool(Z, ~Z, None, sym) & ~Z == want_out & ~Z
            assert pool(Z, None, game.within(S), sym) == want_in
    finally:
        pool.close()
    with pytest.raises(ValueError, match="w cut does not take a symmetry"):
        DaskPredecessors(game, 2, client=client, cut="w")(game.model.x_domain, None, None, sym)


@pytest.mark.slow
def test_with_parts_on_the_cluster_the_domain_is_the_same(client):
    """Consensus N = 4 on two workers: the first call on the representatives in this process, the later ones in
    windows of ŵ on the workers, each closing its own representatives' answer: the pinned domain, the same as with
    the symmetry off."""
    game, phi = _consensus(4)
    phi_domain = {}
    for on in (True, False):
        game.use_symmetry, game._symmetry = on, False
        game.processes, game.parallel_after, game.partitioned = 2, 0.0, on_cluster(client)
        try:
            res = reach_safe(game, phi, layered=True)
            assert game.parallel["calls"] > 0
            phi_domain[on] = (res.domain, res.domain_states)
        finally:
            game.close()
            game._last_pool = None
    assert phi_domain[True] == phi_domain[False]
    assert phi_domain[True][1] == 191_493


def test_closing_in_one_pass_of_bubble_sorts_swaps_is_the_closure_under_every_permutation():
    """``Symmetry.close`` against the fixed point of the adjacent swaps, on random sets of consensus N = 4 (one set
    of four agents: 24 permutations) and on images of single states, whose closure is their orbit."""
    import itertools

    game, _ = _consensus(4)
    sym = game.symmetry
    assert sym is not None and sym.classes == [[0, 1, 2, 3]]
    m, bdd = game.model, game.bdd

    def fixed_point(f):
        while True:
            g = f
            for s in sym.state_swaps:
                g = g | bdd.let(s, g)
            if g == f:
                return f
            f = g

    rng = np.random.default_rng(24)
    for _ in range(6):
        f = _random_set(game, rng, 0.5) & sym.representatives
        assert sym.close(f) == fixed_point(f)
    digits = [m.subsystem_digits(s)["x"][0] for s in m.subsystems]
    for _ in range(4):  # one state: its closure holds exactly the permutations of its codes
        codes = [int(rng.integers(0, m.sizes[d])) for d in digits]
        orbit = {tuple(p) for p in itertools.permutations(codes)}

        def state(cs):
            f = bdd.true
            for d, c in zip(digits, cs):
                f &= m.interval(d, c, c)
            return f

        closed = sym.close(state(codes))
        want = bdd.false
        for p in orbit:
            want |= state(p)
        assert closed == want
