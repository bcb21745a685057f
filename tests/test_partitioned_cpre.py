"""The partitioned ``∃u.CPre`` (pipelines/synthesis/partitioned.py) through each of its transports, local helper
processes (workers/processes/partitioned_cpre.py) and the job's Dask workers (workers/dask_cpre.py), on random
networks: every cut at every position gives the explicit predecessors, and the fixed points give the one-process
domains in every mode."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipelines.symbolic.relations import state_set
from pipelines.synthesis.fixed_points import cobuchi, reach, safe
from pipelines.synthesis.partitioned import PartitionedCPre
from pipelines.synthesis.quotient import quotient
from tests.games import Explicit, build, random_net, random_set, states_vector
from workers.dask_cpre import on_cluster
from workers.processes.partitioned_cpre import PartitionedPredecessors


def partitioned(request: pytest.FixtureRequest, on: str, cut: str = "x"):
    """A ``partitioned`` factory (``factory(cpre, parts)``) of the transport ``on``: ``processes`` (the ``x`` cut
    only) or ``cluster`` (the ``client`` fixture's two workers, with ``cut``)."""
    if on == "processes":
        assert cut == "x"
        return PartitionedPredecessors
    return on_cluster(request.getfixturevalue("client"), cut=cut)


#: (transport, cut, shared w, parts, calls of four sets each, seed): every cut of either transport, more parts than
#: the cluster has workers, the split cut's two phases (from SPLIT_FROM parts on, the shared CPre's 'auto').
CASES = [
    *(pytest.param("processes", "x", shared, 3, 6, 3000 + 10 * seed + shared,
                   id=f"processes-{'shared' if shared else 'per_subsystem'}-{seed}")
      for seed in range(3) for shared in (True, False)),
    *(pytest.param("cluster", "auto", shared, 5, 4, 5100 + shared,
                   id=f"cluster-auto-{'shared' if shared else 'per_subsystem'}") for shared in (True, False)),
    *(pytest.param("cluster", cut, True, 3, 3, 7300 + k, id=f"cluster-{cut}")
      for k, cut in enumerate(("window", "w", "x", "split"))),
]


@pytest.mark.parametrize(("on", "cut", "shared", "parts", "calls", "seed"), CASES)
def test_parts_equal_the_explicit_predecessors(request, on, cut, shared, parts, calls, seed):
    """At every cut position the balancing could choose: ``∃u.CPre(Z)`` exactly, whole, ``within`` a set, on
    ``outside`` (where that argument promises exactness) and on the reach loop's ``outside``, ``¬Z`` (complemented
    by the parts, not sent)."""
    rng = np.random.default_rng(seed)
    net = random_net(rng, shared)
    ex = Explicit(net)
    game = build(net, "shared_top" if shared else ["interleaved", "shared_top"][seed % 2])
    m = game.model
    pool = partitioned(request, on, cut)(game, parts)
    try:
        assert isinstance(pool, PartitionedCPre) and pool.on == on
        assert pool.parts == min(parts, pool.cells) and pool.cells == math.prod(m.sizes[d] for d in pool.digits)
        assert pool.digits[0].startswith("w") == (pool.cut != "x")
        for k in range(calls):
            if k and pool.cells > pool.parts:  # every cut position the balancing could choose
                pool.cuts = sorted(rng.choice(np.arange(1, pool.cells), size=len(pool.cuts), replace=False).tolist())
            Z, S, Out = random_set(rng, ex, 0.6), random_set(rng, ex, 0.7), random_set(rng, ex, 0.5)
            bZ, bS, bO = (state_set(m, np.array(ex.states)[v]) for v in (Z, S, Out))
            want = ex.cpre(Z).any(axis=1)
            np.testing.assert_array_equal(states_vector(m, pool(bZ), ex), want)
            np.testing.assert_array_equal(states_vector(m, pool(bZ, within=game.within(bS)), ex), want & S)
            got = states_vector(m, pool(bZ, outside=bO), ex)
            np.testing.assert_array_equal(got & Out, want & Out)
            got = states_vector(m, pool(bZ, outside=~bZ), ex)
            np.testing.assert_array_equal(got & ~Z, want & ~Z)
        assert pool.calls == 4 * calls and len(pool.seconds) == pool.parts
        report = pool.report()
        assert report["on"] == on and report["calls"] == pool.calls and report["cut"] == pool.cut
        assert report["processes"] == pool.parts and len(report["cuts"]) == pool.parts - 1
    finally:
        pool.close()


def test_cuts_are_checked():
    game = build(random_net(np.random.default_rng(5), True), "shared_top")
    pool = PartitionedCPre(game, 3)
    assert pool.cells > 3
    pool.cuts = [1, pool.cells - 1]
    assert pool.cuts == [1, pool.cells - 1] and pool.cut_cells[0] == (0, 1)
    for bad in ([1], [2, 2], [0, 2], [1, pool.cells]):
        with pytest.raises(ValueError, match="strictly increasing cuts"):
            pool.cuts = bad
    with pytest.raises(NotImplementedError):  # the plan alone moves nothing
        pool(game.model.x_domain)


@pytest.mark.parametrize("shared", [True, False], ids=["shared_w", "per_subsystem_w"])
def test_fixed_points_give_the_same_domains_in_every_mode(request, shared):
    """One process, helper processes and the cluster (two and five parts): the same safe, reach and co-Büchi
    domains, on one model, so the BDDs themselves are compared; and the same for the quotient of level 1
    (pipelines/synthesis/quotient.py), whose parts carry its own relations."""
    rng = np.random.default_rng(91 + shared)
    net = random_net(rng, shared)
    ex = Explicit(net)
    game = build(net, "shared_top" if shared else "interleaved")
    S, T, phi = (state_set(game.model, np.array(ex.states)[v]) for v in
                 (random_set(rng, ex, 0.8), random_set(rng, ex, 0.2), random_set(rng, ex, 0.6)))
    modes = {"one process": (1, None, ""), "processes": (2, partitioned(request, "processes"), "processes"),
             "cluster, 2 parts": (2, partitioned(request, "cluster", "auto"), "cluster"),
             "cluster, 5 parts": (5, partitioned(request, "cluster", "auto"), "cluster")}
    domains = {}
    for name, (parts, factory, on) in modes.items():
        game.processes, game.parallel_after, game.partitioned = parts, 0.0, factory
        q = quotient(game, 1)
        try:
            domains[name] = [safe(game, S, layered=True).domain, reach(game, T, layered=True).domain,
                             cobuchi(game, phi).domain, safe(q, S, layered=True).domain,
                             reach(q, T, layered=True).domain, cobuchi(q, phi).domain]
        finally:
            q.close()
            game.close()
        for g in (game, q):  # still reported after close
            assert (g.parallel.get("on", ""), g.parallel.get("calls", 0) > 0) == (on, bool(on)), name
    first = domains.pop("one process")
    assert states_vector(game.model, first[0], ex).any()  # a game worth comparing
    assert states_vector(game.model, first[4], ex).any() and first[4] != first[1]  # and a quotient that differs
    for name, got in domains.items():
        assert got == first, name
