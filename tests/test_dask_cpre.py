"""Synthesis on the job's Dask cluster (workers/dask_cpre.py): a real two-worker cluster, exact results, the same
domains as in one process and in helper processes, and a clear fallback when the cluster fails."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from pipelines.errors import SpecError
from pipelines.spec.model import parse_spec
from pipelines.symbolic.relations import state_set
from pipelines.synthesis.cpre import PartitionFailed
from pipelines.synthesis.fixed_points import cobuchi, reach, reach_safe, safe
from pipelines.synthesis.quotient import quotient
from pipelines.synthesis.synthesize import synthesize
from tests.test_synthesis import Explicit, build, random_net, random_set, states_vector
from workers.control import partitioning
from workers.dask_cpre import SPLIT_FROM, DaskPartFailed, DaskPredecessors, cut_digits, on_cluster, parts_for
from workers.job import run_abstraction, run_job
from workers.processes.partitioned_cpre import PartitionedPredecessors

from .conftest import EXAMPLES


@pytest.mark.parametrize("shared", [True, False], ids=["shared_w", "per_subsystem_w"])
def test_parts_on_the_cluster_equal_the_explicit_predecessors(client, shared):
    """More parts than workers, at every cut the balancing could choose: ``∃u.CPre(Z)`` exactly, whole, ``within``
    a set and on ``outside``."""
    rng = np.random.default_rng(5100 + shared)
    net = random_net(rng, shared)
    ex = Explicit(net)
    game = build(net, "shared_top" if shared else "interleaved")
    m = game.model
    pool = DaskPredecessors(game, 5, client=client)
    try:
        assert pool.parts == min(5, pool.cells) and pool.cells == math.prod(m.sizes[d] for d in pool.digits)
        for k in range(4):
            if k and pool.cells > pool.parts:
                pool._cuts = sorted(rng.choice(np.arange(1, pool.cells), size=len(pool.cuts), replace=False).tolist())
            Z, S, Out = random_set(rng, ex, 0.6), random_set(rng, ex, 0.7), random_set(rng, ex, 0.5)
            bZ, bS, bO = (state_set(m, np.array(ex.states)[v]) for v in (Z, S, Out))
            want = ex.cpre(Z).any(axis=1)
            np.testing.assert_array_equal(states_vector(m, pool(bZ), ex), want)
            np.testing.assert_array_equal(states_vector(m, pool(bZ, within=game.within(bS)), ex), want & S)
            got = states_vector(m, pool(bZ, outside=bO), ex)
            np.testing.assert_array_equal(got & Out, want & Out)
        assert pool.calls == 12 and len(pool.seconds) == pool.parts
    finally:
        pool.close()


@pytest.mark.parametrize("shared", [True, False], ids=["shared_w", "per_subsystem_w"])
def test_fixed_points_give_the_same_domains_in_every_mode(client, shared):
    """One process, helper processes and the cluster (two and five parts): the same safe, reach and co-Büchi
    domains, on one model, so the BDDs themselves are compared; and the same for the quotient of level 1
    (pipelines/synthesis/quotient.py), whose parts carry its own relations."""
    rng = np.random.default_rng(91 + shared)
    net = random_net(rng, shared)
    ex = Explicit(net)
    game = build(net, "shared_top" if shared else "interleaved")
    S, T, phi = (state_set(game.model, np.array(ex.states)[v]) for v in
                 (random_set(rng, ex, 0.8), random_set(rng, ex, 0.2), random_set(rng, ex, 0.6)))
    modes = {"one process": (1, None), "processes": (2, PartitionedPredecessors),
             "cluster, 2 parts": (2, on_cluster(client)), "cluster, 5 parts": (5, on_cluster(client))}
    domains = {}
    for name, (parts, factory) in modes.items():
        game.processes, game.parallel_after, game.partitioned = parts, 0.0, factory
        q = quotient(game, 1)
        try:
            domains[name] = [safe(game, S, layered=True).domain, reach(game, T, layered=True).domain,
                             cobuchi(game, phi).domain, safe(q, S, layered=True).domain,
                             reach(q, T, layered=True).domain, cobuchi(q, phi).domain]
            if factory is not None:
                for g in (game, q):
                    assert g.parallel["calls"] > 0, name
                    assert g.parallel["on"] == ("processes" if factory is PartitionedPredecessors else "cluster")
        finally:
            q.close()
            game.close()
            game._last_pool = None
    first = domains.pop("one process")
    assert states_vector(game.model, first[0], ex).any()  # a game worth comparing
    assert states_vector(game.model, first[4], ex).any() and first[4] != first[1]  # and a quotient that differs
    for name, got in domains.items():
        assert got == first, name


@pytest.mark.parametrize("cut", ["window", "split", "w", "x"])
def test_every_cut_of_the_shared_cpre_is_exact(client, cut):
    """The shared CPre cut along ``ŵ`` (windows: each part final on its states; split: bad inputs of exact ranges,
    each window's states joined from the ranges it reaches on a worker; or bad inputs joined before ``∃u`` here)
    and along the states: the explicit predecessors, whole, ``within`` a set and on ``outside``, at random cuts."""
    rng = np.random.default_rng(7300 + ["window", "w", "x", "split"].index(cut))
    net = random_net(rng, True)
    ex = Explicit(net)
    game = build(net, "shared_top")
    m = game.model
    pool = DaskPredecessors(game, 3, client=client, cut=cut)
    try:
        assert pool.cut == cut and (pool.digits[0].startswith("w") == (cut != "x"))
        for k in range(3):
            if k and pool.cells > pool.parts:
                pool._cuts = sorted(rng.choice(np.arange(1, pool.cells), size=len(pool.cuts), replace=False).tolist())
            Z, S, Out = random_set(rng, ex, 0.6), random_set(rng, ex, 0.7), random_set(rng, ex, 0.5)
            bZ, bS, bO = (state_set(m, np.array(ex.states)[v]) for v in (Z, S, Out))
            want = ex.cpre(Z).any(axis=1)
            np.testing.assert_array_equal(states_vector(m, pool(bZ), ex), want)
            np.testing.assert_array_equal(states_vector(m, pool(bZ, within=game.within(bS)), ex), want & S)
            got = states_vector(m, pool(bZ, outside=bO), ex)
            np.testing.assert_array_equal(got & Out, want & Out)
            # the reach loop's outside, ¬Z, is complemented on the workers, not sent (dask_parts.NOT_Z)
            got = states_vector(m, pool(bZ, outside=~bZ), ex)
            np.testing.assert_array_equal(got & ~Z, want & ~Z)
    finally:
        pool.close()


def test_the_split_cuts_second_phase_reads_its_own_range_where_it_was_computed():
    """The parts called in this process as a worker calls them: each first phase keeps its answer
    (``dask_parts._KEPT``), the second phase of its range takes it from there (and drops it) and reads the other
    ranges' answers from their bytes; the joined answers are the explicit predecessors whether the answers were
    kept or every one was read from bytes."""
    from pipelines.symbolic.model import Function
    from pipelines.synthesis.partition import admitting_below
    from workers import dask_parts
    from workers.dask_parts import _KEPT, _dump, _load, core_part, join_part

    rng = np.random.default_rng(7400)
    net = random_net(rng, True)
    ex = Explicit(net)
    game = build(net, "shared_top")
    m = game.model
    pool = DaskPredecessors(game, 3, client=None, cut="split")
    key, problem = "test-split-kept", pool.problem()
    try:
        bounds, starts = pool.bounds(), pool._starts()
        ranges = list(zip(starts[:-1], starts[1:]))
        for _ in range(3):
            Z = random_set(rng, ex, 0.6)
            blob = _dump(m, state_set(m, np.array(ex.states)[Z]))
            want = ex.cpre(Z).any(axis=1)
            for kept in (True, False):
                _KEPT.clear()
                cores = [core_part(key, problem, blob, None, list(pool.digits), list(a), None if b is None else list(b))
                         for a, b in ranges]
                assert all(c.kept in _KEPT for c in cores) and len(_KEPT) == len(cores)
                if not kept:
                    _KEPT.clear()  # every range read from its bytes, as on another worker
                joins = []
                for k, (a, b) in enumerate(ranges):
                    reached = pool._reached(k, bounds)
                    joins.append(join_part(key, problem, list(pool.digits), list(a), None if b is None else list(b),
                                           None, *(cores[j] for j in reached)))
                    assert cores[k].kept not in _KEPT  # its own range's answer is dropped once read
                got: Function = m.bdd.false
                for j in joins:
                    got |= _load(m, j.blob)
                np.testing.assert_array_equal(states_vector(m, got, ex), want)
        # the states of a range come from sets the worker keeps with the problem, one per code, as computed afresh
        held = dask_parts._HELD[key]
        assert held.M is not None and held.memo and {k[0] for k in held.memo} == {"below"}
        for (_, digit, c), f in held.memo.items():
            assert f == admitting_below(held.model, held.M, digit, c)
    finally:
        pool.close()
        _KEPT.clear()
        dask_parts.forget(problem["model"])


def test_a_worker_that_lost_its_problem_is_sent_it_again(client):
    """The problem reaches the workers once (``dask_parts.receive``), not as a dependency of every part; a worker
    without it (restarted, or joined since) fails its part with ``ProblemMissing``, and the call sends the problem
    to every worker again and runs on the cluster, exactly."""
    from workers.dask_parts import forget

    rng = np.random.default_rng(7500)
    net = random_net(rng, True)
    ex = Explicit(net)
    game = build(net, "shared_top")
    m = game.model
    pool = DaskPredecessors(game, 2, client=client)
    try:
        for k in range(2):
            if k:  # one worker forgets every problem of this CPre, as if it had restarted
                first = pool._problem_key
                lost = client.run(forget, pool._model_key, workers=[sorted(client.nthreads())[0]])
                assert list(lost.values()) == [1]
            Z = random_set(rng, ex, 0.6)
            got = states_vector(m, pool(state_set(m, np.array(ex.states)[Z])), ex)
            np.testing.assert_array_equal(got, ex.cpre(Z).any(axis=1))
        assert pool.calls == 2 and pool._problem_key != first  # on the cluster both times, the problem sent again
    finally:
        pool.close()


def test_a_problem_pushed_out_of_a_workers_memory_is_loaded_again_from_what_was_sent():
    """Three CPres' problems on one worker (jobs sharing a cluster): the worker keeps two loaded
    (``HELD_PROBLEMS``), and the first, pushed out, is loaded again from the bytes it was sent, with the same
    relations; one never sent is ``ProblemMissing``."""
    from workers.dask_parts import _HELD, HELD_PROBLEMS, ProblemMissing, _dump, _load, _problem, forget, receive

    rng = np.random.default_rng(7600)
    games = [build(random_net(rng, True), "shared_top") for _ in range(3)]
    pools = [DaskPredecessors(g, 2, client=None) for g in games]
    keys = [f"test-sent-{k}" for k in range(3)]
    try:
        for key, pool in zip(keys, pools):
            receive(key, pool.problem())
            _problem(key, None)
        assert HELD_PROBLEMS == 2 and keys[0] not in _HELD and all(k in _HELD for k in keys[1:])
        model, chain, *_ = _problem(keys[0], None)
        game = games[0]
        assert len(chain) == len(game.chain)
        for (rel, _), (want, _) in zip(chain, game.chain):  # the same relations, in the worker's own manager
            assert _load(game.model, _dump(model, rel)) == want
        with pytest.raises(ProblemMissing, match="not sent"):
            _problem("test-sent-never", None)
    finally:
        for pool in pools:
            pool.close()
            forget(pool._model_key)


def test_the_w_cut_needs_a_shared_internal_variable():
    game = build(random_net(np.random.default_rng(3), False), "interleaved")
    assert game.M is None
    for cut in ("w", "window", "split"):
        with pytest.raises(ValueError, match=f"{cut} cut needs the shared CPre"):
            cut_digits(game, cut)
    assert cut_digits(game)[0] == "x"
    with pytest.raises(ValueError, match="cut must be one of"):
        cut_digits(game, "diagonal")
    shared = build(random_net(np.random.default_rng(4), True), "shared_top")
    assert cut_digits(shared)[0] == "window"


def test_auto_splits_the_shared_cpre_from_split_from_parts_on(client):
    """``cut='auto'`` on the shared CPre: windows below :data:`SPLIT_FROM` parts, the split cut from there on (its
    parts run the chain on each cell of ``ŵ`` once; the windows overlap)."""
    game = build(random_net(np.random.default_rng(4), True), "shared_top")
    pools = [DaskPredecessors(game, 2, client=client), DaskPredecessors(game, SPLIT_FROM, client=client),
             DaskPredecessors(game, SPLIT_FROM, client=client, cut="window")]
    try:
        assert [p.cut for p in pools] == ["window", "split", "window"]
    finally:
        for p in pools:
            p.close()


@pytest.mark.parametrize("cut", ["window", "split"])
def test_a_closed_cluster_is_a_clear_failure_and_the_game_goes_on_here(cut):
    """The cluster goes away between calls: the part fails as a PartitionFailed naming the cluster, and the
    fixed point answers in this process, exactly (also where the parts are two phases, the split cut)."""
    from workers.cluster import connect

    rng = np.random.default_rng(17)
    net = random_net(rng, True)
    ex = Explicit(net)
    game = build(net, "shared_top")
    Z = state_set(game.model, np.array(ex.states)[random_set(rng, ex, 0.6)])
    want = game.predecessors(Z)
    conn = connect(None, 1)
    try:
        pool = DaskPredecessors(game, 2, client=conn.client, cut=cut)
        assert pool(Z) == want
    finally:
        conn.close()
    with pytest.raises(DaskPartFailed, match="Dask") as info:
        pool(Z)
    assert isinstance(info.value, PartitionFailed)
    # The traceback holds this frame, whose sets it would keep in a cycle; the garbage collector may then free the
    # BDD manager before them (dd: "nodes referenced upon shutdown").
    del info
    # through the game: the failure is reported and the later calls run here
    game._pool, game.processes = pool, 2
    assert game.predecessors(Z) == want
    assert "Dask" in game.parallel["stopped"] and game.processes == 1
    assert game.predecessors(Z) == want


def _consensus(N: int, **options) -> str:
    data = yaml.safe_load((EXAMPLES / "consensus.yaml").read_text())
    data["parameters"]["N"] = N
    data["options"].update({"initial_states": [[15.0] * N], "audit_transitions": 0, "closed_loop_runs": 20,
                            **options})
    return yaml.safe_dump(data)


@pytest.mark.slow
def test_consensus_on_the_cluster_gives_the_one_process_domain(client):
    """Consensus N = 4 (shared ``w``, Reach(Safe)): the same domain BDD on the cluster (two and three parts per
    worker) as in one process; the parts ran on the workers."""
    spec = parse_spec(_consensus(4))
    a = run_abstraction(spec, audit=False)
    one, results, _ = synthesize(a.network, a.relations, a.interconnection, spec.specification,
                                 reach_and_stay_methods=("reach_safe",), processes=1)
    want = results["reach_safe"].domain_states
    assert want == 191_493  # tests/test_pinned_numbers.py
    for per_worker in (1, 3):
        game, got, report = synthesize(a.network, a.relations, a.interconnection, spec.specification,
                                       reach_and_stay_methods=("reach_safe",), processes="auto",
                                       partitioned=on_cluster(client), auto_parts=parts_for(client, per_worker),
                                       parallel_after=0.0)
        try:
            assert got["reach_safe"].domain_states == want
            assert report["parallel"]["on"] == "cluster" and report["parallel"]["processes"] == 2 * per_worker
            assert report["parallel"]["calls"] > 0
            t = report["parallel"]["seconds"]  # the breakdown bench/synthesis.py prints
            assert set(t) == {"sending", "slowest_part", "slowest_part_cpu", "after_parts", "exists_u", "last_start",
                              "last_entered", "after_last"}
            assert t["slowest_part"] > 0 and t["last_start"] >= t["last_entered"] >= 0 and t["after_last"] >= 0
            # CPU seconds of the parts' threads: some, and (thread time) not more than their wall seconds
            assert 0 < t["slowest_part_cpu"] <= t["slowest_part"] * 1.05 + 0.05
            calls = report["parallel"]["per_call"]
            assert len(calls) == report["parallel"]["calls"] and all(c["wall"] >= c["slowest_part"] for c in calls)
            # one part per worker at a time, handed out as workers free up (workers.dispatch), none queued behind
            # another's; with a part per worker, each on a worker of its own
            assert [c["most_in_flight"] for c in calls] == [2] * len(calls)
            if per_worker == 1:
                assert [c["most_on_one_worker"] for c in calls] == [1] * len(calls)
            # what the busiest worker ran in a call, one task after another, within the call
            assert all(0 < c["busiest_worker"] <= c["parts_span"] + 0.05 <= c["wall"] + 0.1 for c in calls)
            assert all(0 < c["busiest_worker_cpu"] <= c["busiest_worker"] * 1.05 + 0.05 for c in calls)
            # the window cut's parts cover every cell of ŵ, some twice (the windows overlap by M̂'s spread)
            w = report["parallel"]["window_cells"]
            assert len(w["parts"]) == 2 * per_worker and w["cells"] == 33
            assert w["cells"] <= sum(w["parts"]) <= 2 * per_worker * w["cells"]
        finally:
            game.close()


@pytest.mark.slow
def test_a_job_synthesizes_on_its_cluster(tmp_path, client):
    """``run_job`` on a cluster keeps it for synthesis: the report says the parts ran there, and the domain is the
    one process's."""
    spec = parse_spec(_consensus(4, synthesis_parallel_after=0.0, fixed_points=["reach_safe"],
                                 controller="reach_safe"))
    report = run_job(spec, tmp_path / "job", client=client)
    assert report["domain_states"] == 191_493
    assert report["synthesis"]["parallel"]["on"] == "cluster"
    assert report["synthesis"]["parallel"]["calls"] > 0
    assert client.status == "running"  # a caller's client stays open


def test_where_synthesis_runs_follows_the_options(client):
    spec = parse_spec(_consensus(3))
    assert partitioning(spec.options)["partitioned"] is PartitionedPredecessors
    on = partitioning(spec.options, client)
    assert on["auto_parts"] == parts_for(client) == 2 and on["partitioned"] is not PartitionedPredecessors
    spec = parse_spec(_consensus(3, synthesis_on="processes"))
    assert partitioning(spec.options, client)["partitioned"] is PartitionedPredecessors
    spec = parse_spec(_consensus(3, synthesis_on="cluster"))
    with pytest.raises(SpecError, match="synthesis_on is 'cluster' but this job has no Dask cluster"):
        partitioning(spec.options)


def test_reach_safe_on_the_cluster_of_a_shared_game(client):
    """The fixed point the consensus case runs, on a random shared-``w`` game, with more parts than workers."""
    rng = np.random.default_rng(23)
    net = random_net(rng, True)
    ex = Explicit(net)
    game = build(net, "shared_top")
    phi = state_set(game.model, np.array(ex.states)[random_set(rng, ex, 0.7)])
    want = reach_safe(game, phi, layered=True).domain
    game.processes, game.parallel_after, game.partitioned = 4, 0.0, on_cluster(client)
    try:
        assert reach_safe(game, phi, layered=True).domain == want
        assert game.parallel["calls"] > 0
    finally:
        game.close()
