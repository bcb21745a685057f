"""Local games (pipelines/synthesis/local_games.py): their bound contains the maximal invariant, and the safety fixed
points started from it give the same invariant and controllers as from the safe set (and as the explicit solver)."""

from __future__ import annotations

import numpy as np
import pytest

from pipelines.abstraction.relation import SubsystemRelation
from pipelines.symbolic.order import SubsystemLayout
from pipelines.symbolic.relations import state_set
from pipelines.synthesis import local_games
from pipelines.synthesis.fixed_points import reach_and_stay, safe
from pipelines.synthesis.local_games import invariant_bound, local_game, local_groups

from .games import (
    Explicit,
    Net,
    build,
    coupled_net,
    random_set,
    states_vector,
)
from .strategies import random_node


def _case(seed: int, shared: bool):
    rng = np.random.default_rng(7000 + 100 * shared + seed)
    net = coupled_net(rng, shared)
    game = build(net, ["interleaved", "shared_top"][seed % 2], "shared" if shared else "auto")
    return rng, net, game


@pytest.mark.parametrize("shared", [False, True], ids=["per_subsystem_w", "shared_w"])
def test_the_bound_contains_the_invariant_and_the_fixed_points_do_not_change(shared, monkeypatch):
    """Over 24 random coupled networks: ``W ⊆ bound ⊆ S``; ``safe`` and Reach(Safe) from the bound (used whatever
    share of ``S`` it keeps) give the domains and controllers they give from ``S``, which the explicit solver gives;
    and some bound is strictly inside ``S`` (else nothing here would test the games)."""
    monkeypatch.setattr(local_games, "USE_BELOW", 1.0)
    tighter = 0
    for seed in range(24):
        rng, net, game = _case(seed, shared)
        m = game.model
        ex = Explicit(net)
        S, phi = random_set(rng, ex, 0.9), random_set(rng, ex, 0.75)
        bS, bphi = (state_set(m, np.array(ex.states)[v]) for v in (S, phi))

        plain = safe(game, bS, local_games=False)
        fast = safe(game, bS)
        assert fast.domain == plain.domain and fast.controller == plain.controller
        np.testing.assert_array_equal(states_vector(m, fast.domain, ex), ex.safe(S))
        bound = invariant_bound(game, bS & m.x_domain).bound
        assert plain.domain & ~bound == game.bdd.false, f"seed {seed}: the bound cut off an invariant state"
        assert bound & ~bS == game.bdd.false
        tighter += bound != (bS & m.x_domain)
        assert fast.details["local_games"]["groups"] == [list(g.members) for g in local_groups(game)]
        assert fast.details["local_games"]["used"] == (bound != (bS & m.x_domain))

        both = reach_and_stay(game, bphi, ("reach_safe",))["reach_safe"]
        without = reach_and_stay(game, bphi, ("reach_safe",), local_games=False)["reach_safe"]
        assert both.domain == without.domain and both.controller == without.controller
        np.testing.assert_array_equal(states_vector(m, both.domain, ex), ex.reach(ex.safe(phi)))
    assert tighter >= 6, f"only {tighter} of 24 bounds were tighter than S"


def test_each_local_game_contains_the_projection_of_the_invariant():
    """The proof's step, game by game, over 12 random networks: the greatest fixed point of a local game inside ``S``
    contains the projection of the maximal invariant on the game's subsystems (and lies in the projection of
    ``S``)."""
    checked = 0
    for seed in range(12):
        rng, net, game = _case(seed, bool(seed % 2))
        m, bdd = game.model, game.bdd
        ex = Explicit(net)
        bS = state_set(m, np.array(ex.states)[random_set(rng, ex, 0.9)]) & m.x_domain
        W = safe(game, bS, local_games=False).domain
        for group in local_groups(game):
            own = set(m.bits_of([f"x{i}" for i in group.members]))
            others = [b for b in m.x_bits if b not in own]
            Y, iterations = local_game(game, group, bS)
            assert iterations >= 1
            assert bdd.exist(others, W) & ~Y == bdd.false, f"seed {seed}: group {group.members} lost an invariant state"
            assert Y & ~bdd.exist(others, bS) == bdd.false
            checked += 1
    assert checked >= 24, f"only {checked} local games checked"


def test_groups_are_a_subsystem_and_the_ones_it_reads_at_most_half_the_network(monkeypatch):
    """Tanks-like cascade 0 -> 1 -> 2 -> 3 -> 4 -> 5 (each reads the one before): the groups are {0}, {0, 1}, ...,
    {4, 5}; a network where one subsystem reads four others has no group for it; groups above MAX_GROUP_BITS state
    bits are left out."""
    rng = np.random.default_rng(3)
    N = 6
    shape, n_u = (3,) * N, (2,) * N
    nodes, reads = [], [()]
    for i in range(1, N):
        nodes.append(random_node(rng, f"w{i - 1}", 2, [f"x{i - 1}"], [3], 0.0))
        reads.append((i - 1,))
    here = np.arange(3).reshape(-1, 1, 1, 1)
    layouts, relations = [], {}
    for i in range(N):
        n_w = 2 if reads[i] else 1
        lo = np.clip(here + np.zeros((3, 2, n_w, 1), dtype=int), 0, 2)
        layouts.append(SubsystemLayout(i, (3,), 2, reads[i], f"k{i}", i))
        relations[f"k{i}"] = SubsystemRelation("test", lo.astype(np.int32), lo.astype(np.int32),
                                               np.zeros((3, 2, n_w), bool), 1, 1)
    game = build(Net(layouts, relations, [2] * (N - 1), nodes, shape, n_u), "interleaved")
    assert [g.members for g in local_groups(game)] == [(0,), (0, 1), (1, 2), (2, 3), (3, 4), (4, 5)]

    nodes[-1] = random_node(rng, "w4", 2, ["x0", "x1", "x2", "x3"], [3] * 4, 0.0)  # subsystem 5 reads four others
    game = build(Net(layouts, relations, [2] * (N - 1), nodes, shape, n_u), "interleaved")
    assert [g.members for g in local_groups(game)] == [(0,), (0, 1), (1, 2), (2, 3), (3, 4)]
    monkeypatch.setattr(local_games, "MAX_GROUP_BITS", 3)  # 2 bits per subsystem: single subsystems only
    assert [g.members for g in local_groups(game)] == [(0,)]


def test_a_bound_that_keeps_more_than_half_of_the_safe_set_is_not_started_from():
    """The bound is started from only when it keeps at most USE_BELOW of S (a loose bound has many more nodes than
    S and made the first iterates larger); the share is exact, and the invariant is the same either way."""
    seen = set()
    for seed in range(24):
        rng, net, game = _case(seed, False)
        m = game.model
        ex = Explicit(net)
        bS = state_set(m, np.array(ex.states)[random_set(rng, ex, 0.9)]) & m.x_domain
        found = invariant_bound(game, bS)
        if found.bound == bS:
            continue
        share = states_vector(m, found.bound, ex).sum() / states_vector(m, bS, ex).sum()
        assert found.share == pytest.approx(share)
        assert found.used == (share <= local_games.USE_BELOW)
        seen.add(found.used)
        assert found.start == (found.bound if found.used else bS)
        assert safe(game, bS).domain == safe(game, bS, local_games=False).domain
    assert seen == {True, False}, f"only bounds with used = {seen}"
