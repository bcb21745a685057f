"""The quotient game (pipelines/synthesis/quotient.py): blocks of 2^k cells per coordinate, sound for the fine game.

Over random networks (per-subsystem and shared internal variables) the quotient's relations contain the fine ones
and forget the merged bits, its CPre lies inside the fine CPre, and every fixed point's controller is checked in
the *fine* explicit game: the invariant is closed under every allowed input, every run of the reach controllers
reaches the target, the reach-and-stay controllers stay. Its domains lie inside the maximal ones, some strictly.
Helper processes give it the same domains as one process. End to end (the tanks at spacing 1.25, slow), the job
runs in seconds, the concrete closed loop has no violation, and the report and warnings say the domain is not
the maximal one.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from pipelines.abstraction.relation import SubsystemRelation
from pipelines.errors import SpecError
from pipelines.spec.model import load_spec, parse_spec, spec_hash
from pipelines.symbolic.order import SubsystemLayout
from pipelines.symbolic.relations import state_set
from pipelines.synthesis.fixed_points import reach, reach_and_stay, reach_avoid, safe
from pipelines.synthesis.quotient import Refinement, dilate, merged_bits, neighbours, quotient
from workers.checkpoint_store import problem_key
from workers.processes.partitioned_cpre import PartitionedPredecessors

from .conftest import EXAMPLES
from .games import (
    Explicit,
    Net,
    build,
    check_progress,
    check_stay,
    controller_matrix,
    random_net,
    random_set,
    states_vector,
)


def _game(seed: int, shared: bool, blocking: bool = True):
    """A random network of tests/test_synthesis.py and its games; ``blocking=False``: no triple blocks (a block of
    cells with one blocking triple loses that input, so on random relations the quotient's invariants are then
    mostly empty)."""
    rng = np.random.default_rng(4400 + 100 * shared + seed)
    net = random_net(rng, shared)
    if not blocking:
        for rel in net.relations.values():
            here = np.broadcast_to(np.arange(rel.lo.shape[0]).reshape(-1, 1, 1, 1), rel.lo.shape)
            rel.lo[rel.blocking], rel.hi[rel.blocking] = here[rel.blocking], here[rel.blocking]
            rel.blocking[:] = False
    return rng, net, Explicit(net), build(net, ["interleaved", "shared_top"][seed % 2])


def block_set(rng, ex: Explicit, k: int, p: float) -> np.ndarray:
    """A random set of whole blocks of 2^k cells per coordinate (a random cell set is rarely one: its quotient
    would be empty)."""
    blocks = np.array(ex.states) >> k
    keys, inverse = np.unique(blocks, axis=0, return_inverse=True)
    return (rng.random(len(keys)) < p)[inverse.reshape(-1)]


def _subset(a, b) -> bool:
    return a & ~b == a.bdd.false


@pytest.mark.parametrize("shared", [False, True], ids=["per_subsystem_w", "shared_w"])
def test_the_quotient_contains_the_fine_relations_and_forgets_the_merged_bits(shared):
    for seed in range(10):
        rng, _, ex, game = _game(seed, shared)
        m, bdd = game.model, game.bdd
        assert quotient(game, 0) is game
        for k in (1, 2):
            q = quotient(game, k)
            low, low_next = merged_bits(m, k)
            # each coordinate's k lowest bits (all of them where it has fewer), next-state bits alike
            want = [b for d in m.x_digits() for b in m.bits[d][-k:]]
            assert low == want and low_next == [b.replace("x", "xn", 1) for b in want]
            for (rel, xn), (rq, xnq) in zip(game.chain, q.chain):
                # containing the fine relation, reading no merged current bit, the same on every successor cell
                # of a block on the grid
                assert xn == xnq and _subset(rel, rq) and not set(low) & set(bdd.support(rq))
                own = [d for d in m.xn_digits() if set(m.bits[d]) & set(xn)]
                assert rq == bdd.exist(low_next, rq) & m.domain(own)
            # inside the fine admissible pairs, and the same at every cell of a block on the grid
            assert _subset(q.admissible, game.admissible)
            assert q.admissible == m.x_domain & bdd.exist(low, q.admissible)
            if game.M is not None:
                assert q.M is not None and _subset(game.M, q.M) and not set(low) & set(bdd.support(q.M))
            assert q.level == k and game.level == 0 and q.model is m
            # CPre^q(Z) ⊆ CPre(Z) for any Z, blocks or not
            for _ in range(3):
                Z = state_set(m, np.array(ex.states)[random_set(rng, ex, 0.7)])
                assert _subset(q.cpre(Z), game.cpre(Z))
                assert _subset(q.predecessors(Z), game.predecessors(Z))
    with pytest.raises(ValueError, match="at least 0"):
        quotient(game, -1)


@pytest.mark.parametrize("shared", [False, True], ids=["per_subsystem_w", "shared_w"])
def test_the_quotients_controllers_win_the_fine_game(shared):
    """40 random networks (half without blocking triples), levels 1 and 2: each controller checked in the fine
    explicit game, each domain inside the maximal one; some quotient invariants are non-empty and some smaller
    than the maximal ones (the sets are unions of blocks, as a box on the coarse grid is)."""
    nonempty = smaller = 0
    for seed in range(40):
        rng, _, ex, game = _game(seed, shared, blocking=bool(seed % 2))
        m = game.model
        for k in (1, 2):
            S, T, phi = (block_set(rng, ex, k, p) for p in (0.95, 0.3, 0.9))
            A = random_set(rng, ex, 0.1)
            bS, bT, bA, bphi = (state_set(m, np.array(ex.states)[v]) for v in (S, T, A, phi))
            q = quotient(game, k)
            r = safe(q, bS)
            dom = states_vector(m, r.domain, ex)
            C = controller_matrix(m, r.controller, ex)
            assert not np.any(dom & ~ex.safe(S)), f"seed {seed}: a quotient invariant state the fine game loses"
            assert np.all(C.any(axis=1)[dom]) and not np.any(C[~dom])
            assert not np.any(C & ~ex.cpre(dom)), "an allowed input leaves the invariant in the fine game"
            nonempty += bool(dom.any())
            smaller += int(dom.sum()) < int(ex.safe(S).sum())

            r = reach(q, bT, safe=bS)
            dom = states_vector(m, r.domain, ex)
            assert not np.any(dom & ~ex.reach(T, ~S))
            check_progress(ex, controller_matrix(m, r.controller, ex), dom, T & S)

            r = reach_avoid(q, bT, bA)
            dom = states_vector(m, r.domain, ex)
            assert not np.any(dom & ~ex.reach(T, A))
            check_progress(ex, controller_matrix(m, r.controller, ex), dom, T & ~A)

            for name, res in reach_and_stay(q, bphi).items():
                dom = states_vector(m, res.domain, ex)
                assert not np.any(dom & ~ex.reach(ex.safe(phi))), name
                check_stay(ex, controller_matrix(m, res.controller, ex), dom, phi)
    assert nonempty >= 8 and smaller >= 10, (nonempty, smaller)


def test_a_block_the_grid_cuts_short_keeps_its_cells():
    """Two subsystems of 5 and 7 cells that stay where they are: every cell is invariant, in the fine game and in
    the quotients of levels 1 and 2, whose last blocks hold 1 and 3 of their codes (the others are off the grid)."""
    layouts, relations = [], {}
    for i, n in enumerate((5, 7)):
        here = np.arange(n, dtype=np.int32).reshape(-1, 1, 1, 1)
        relations[f"k{i}"] = SubsystemRelation("test", here.copy(), here.copy(), np.zeros((n, 1, 1), bool), 1, 1)
        layouts.append(SubsystemLayout(i, (n,), 1, (), f"k{i}", i))
    net = Net(layouts, relations, [], [], (5, 7), (1, 1))
    ex = Explicit(net)
    game = build(net, "interleaved")
    everything = state_set(game.model, np.array(ex.states))
    for k in (0, 1, 2):
        assert safe(quotient(game, k), everything).domain_states == 35, k


@pytest.mark.parametrize("shared", [True, False], ids=["shared_w", "per_subsystem_w"])
def test_the_quotient_with_helper_processes_gives_the_one_process_domains(shared):
    rng = np.random.default_rng(91 + shared)
    net = random_net(rng, shared)
    ex = Explicit(net)
    S, T, phi = (random_set(rng, ex, p) for p in (0.85, 0.25, 0.7))
    one = quotient(build(net, "shared_top" if shared else "interleaved"), 1)
    fine = build(net, "shared_top" if shared else "interleaved")
    fine.processes, fine.parallel_after, fine.partitioned = 2, 0.0, PartitionedPredecessors
    two = quotient(fine, 1)  # the quotient starts its own helpers, with its own relations
    try:
        for g in (one, two):
            g.results = []
            bS, bT, bphi = (state_set(g.model, np.array(ex.states)[v]) for v in (S, T, phi))
            g.results.append(safe(g, bS, layered=True).domain)
            g.results.append(reach(g, bT, layered=True).domain)
            g.results.append(reach_and_stay(g, bphi, ("reach_safe",), layered=True)["reach_safe"].domain)
        for a, b in zip(one.results, two.results):
            np.testing.assert_array_equal(states_vector(one.model, a, ex), states_vector(two.model, b, ex))
        assert two.parallel["calls"] > 0 and fine.parallel == {}
    finally:
        two.close()
        fine.close()


def with_quotient(path, k):
    data = yaml.safe_load(path.read_text())
    data["options"]["synthesis_quotient"] = k
    return parse_spec(data)


def test_the_option_is_checked_and_keeps_the_abstraction_but_not_the_iterates():
    base = load_spec(EXAMPLES / "tanks.yaml")
    assert base.options.synthesis_quotient == 0
    with_q = with_quotient(EXAMPLES / "tanks.yaml", 1)
    assert with_q.options.synthesis_quotient == 1
    assert spec_hash(with_q) == spec_hash(base)  # the stored abstraction is reused
    for bad in (-1, 17, "one"):
        with pytest.raises(SpecError, match="synthesis_quotient"):
            with_quotient(EXAMPLES / "tanks.yaml", bad)
    spec = json.loads(json.dumps(base.specification.model_dump(mode="json")))
    assert problem_key(spec, {}, []) == problem_key(spec, {}, [], quotient=0)
    assert problem_key(spec, {}, [], quotient=1) != problem_key(spec, {}, [])
    assert problem_key(spec, {}, [], quotient=1) != problem_key(spec, {}, [], quotient=2)


@pytest.mark.slow
def test_the_fine_tanks_end_to_end_on_the_quotient(tmp_path):
    """Issue 24: the ten tanks at spacing 1.25 (80^10 cells) end to end with options.synthesis_quotient 1, in
    process: a non-empty domain inside the outer bound, 100 closed-loop runs of the concrete tanks without a
    violation, the paper's initial state outside (as the domain bound proves for the maximal domain), and a
    warning that the domain may be smaller than the maximal one."""
    from workers.executors import Execution
    from workers.job import run_job

    spec = with_quotient(EXAMPLES / "tanks_fine.yaml", 1)
    report = run_job(spec, tmp_path / "job", execution=Execution(in_process=True), audit=False)
    syn = report["synthesis"]
    assert syn["quotient"]["level"] == 1 and syn["quotient"]["maximal"] is False
    assert 0 < report["domain_states"] <= syn["domain_bound"]["domain_states_at_most"]
    assert syn["domain_bound"]["initial_states_outside"] == [{"index": 0, "group": ["tank4", "tank5", "tank7"]}]
    loop = report["closed_loop"]
    assert loop["runs"] == 100 and loop["violations"] == 0
    assert any("synthesis_quotient is 1" in w for w in report["warnings"])


def test_neighbours_are_the_cells_within_one_code():
    _, _, ex, game = _game(3, False)
    m = game.model
    chain = neighbours(m)
    for code in ex.states:
        got = states_vector(m, dilate(m, chain, state_set(m, np.array([code]))), ex)
        want = np.array([max(abs(a - b) for a, b in zip(code, other)) <= 1 for other in ex.states])
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("shared", [False, True], ids=["per_subsystem_w", "shared_w"])
def test_refinement_grows_the_quotients_invariant_soundly(shared):
    """40 random networks (half without blocking triples), level 1: each refined invariant contains the quotient's,
    lies inside the maximal one, and its controller (from the fine CPre) keeps it in the fine explicit game; the
    Reach(Safe) controller from it stays; some rounds grow the invariant."""
    grew = 0
    for seed in range(40):
        rng, _, ex, game = _game(seed, shared, blocking=bool(seed % 2))
        m = game.model
        S, phi = (block_set(rng, ex, 1, p) for p in (0.95, 0.9))
        bS, bphi = (state_set(m, np.array(ex.states)[v]) for v in (S, phi))
        q = quotient(game, 1)
        plain = states_vector(m, safe(q, bS).domain, ex)
        r = safe(q, bS, refine=Refinement(game, 3))
        dom = states_vector(m, r.domain, ex)
        C = controller_matrix(m, r.controller, ex)
        assert not np.any(plain & ~dom) and not np.any(dom & ~ex.safe(S)), seed
        assert np.all(C.any(axis=1)[dom]) and not np.any(C[~dom]) and not np.any(C & ~ex.cpre(dom)), seed
        assert r.details["refinement"]["states_after"] == dom.sum()
        grew += int(dom.sum()) > int(plain.sum())
        res = reach_and_stay(q, bphi, ("reach_safe",), refine=Refinement(game, 3))["reach_safe"]
        check_stay(ex, controller_matrix(m, res.controller, ex), states_vector(m, res.domain, ex), phi)
    assert grew >= 5, grew


def test_refinement_needs_a_quotient():
    data = yaml.safe_load((EXAMPLES / "tanks.yaml").read_text())
    data["options"]["synthesis_refine"] = 1
    with pytest.raises(SpecError, match="synthesis_refine is 1, but it grows the invariant of a quotient"):
        parse_spec(data)
    data["options"]["synthesis_quotient"] = 1
    assert parse_spec(data).options.synthesis_refine == 1
    for bad in (-1, 101, "two"):
        data["options"]["synthesis_refine"] = bad
        with pytest.raises(SpecError, match="synthesis_refine"):
            parse_spec(data)
