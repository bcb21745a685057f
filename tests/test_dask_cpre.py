"""Synthesis on the job's Dask cluster (workers/dask_cpre.py, workers/dask_parts.py): the problem kept on the
workers and sent again when lost, the split cut's answers kept where they were computed, the choice of the cut, a
clear fallback when the cluster fails, and the consensus case's domain on a real two-worker cluster. The parts'
answers, on every cut, are tested with the helper processes' in tests/test_partitioned_cpre.py."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from pipelines.errors import SpecError
from pipelines.spec.model import parse_spec
from pipelines.symbolic.files import from_bytes, to_bytes
from pipelines.symbolic.relations import state_set
from pipelines.synthesis.cpre import PartitionFailed
from pipelines.synthesis.fixed_points import reach_safe
from pipelines.synthesis.options import SynthesisOptions
from pipelines.synthesis.partitioned import SPLIT_FROM, cut_digits
from pipelines.synthesis.parts import Problem, pack
from pipelines.synthesis.synthesize import synthesize
from tests.games import Explicit, build, random_net, random_set, states_vector
from workers.control import partitioning
from workers.dask_cpre import DaskPartFailed, DaskPredecessors, on_cluster, parts_for
from workers.dask_parts import (
    _HELD,
    _KEPT,
    HELD_PROBLEMS,
    ProblemMissing,
    compute_part,
    forget,
    held,
    join_part,
    receive,
)
from workers.executors import Execution
from workers.job import run_abstraction, run_job
from workers.processes.partitioned_cpre import PartitionedPredecessors

from .conftest import EXAMPLES


def test_the_split_cuts_second_phase_reads_its_own_range_where_it_was_computed():
    """The parts called in this process as a worker calls them: each first phase keeps its answer
    (``dask_parts._KEPT``), the second phase of its range takes it from there (and drops it) and reads the other
    ranges' answers from their bytes; the joined answers are the explicit predecessors whether the answers were
    kept or every one was read from bytes."""
    from pipelines.synthesis.partition import admitting_below

    rng = np.random.default_rng(7400)
    net = random_net(rng, True)
    ex = Explicit(net)
    game = build(net, "shared_top")
    m = game.model
    pool = DaskPredecessors(game, 3, client=None, cut="split")
    key, owner = "test-split-kept", "test-split-owner"
    receive(key, pack(Problem.of(game), owner))
    try:
        specs, reads = pool.specs(), pool.reads(pool.bounds())
        assert [s.kind for s in specs] == ["bad"] * 3
        for _ in range(3):
            Z = random_set(rng, ex, 0.6)
            blob = to_bytes(m, state_set(m, np.array(ex.states)[Z]))
            want = ex.cpre(Z).any(axis=1)
            for kept in (True, False):
                _KEPT.clear()
                cores = [compute_part(key, spec, blob, None, keep=True) for spec in specs]
                assert all(c.kept in _KEPT for c in cores) and len(_KEPT) == len(cores)
                if not kept:
                    _KEPT.clear()  # every range read from its bytes, as on another worker
                got = m.bdd.false
                for k, spec in enumerate(specs):
                    got |= from_bytes(m, join_part(key, spec, None, *(cores[j] for j in reads[k])).blob)
                    assert cores[k].kept not in _KEPT  # its own range's answer is dropped once read
                np.testing.assert_array_equal(states_vector(m, got, ex), want)
        # the states of a range come from sets the worker keeps with the problem, one per code, as computed afresh
        problem = held(key)
        assert problem.M is not None and problem.memo and {k[0] for k in problem.memo} == {"below"}
        for (_, digit, c), f in problem.memo.items():
            assert f == admitting_below(problem.model, problem.M, digit, c)
    finally:
        pool.close()
        _KEPT.clear()
        forget(owner)


def test_a_worker_that_lost_its_problem_is_sent_it_again(client):
    """The problem reaches the workers once (``dask_parts.receive``), not as a dependency of every part; a worker
    without it (restarted, or joined since) fails its part with ``ProblemMissing``, and the call sends the problem
    to every worker again and runs on the cluster, exactly."""
    rng = np.random.default_rng(7500)
    net = random_net(rng, True)
    ex = Explicit(net)
    game = build(net, "shared_top")
    m = game.model
    pool = DaskPredecessors(game, 2, client=client)
    try:
        for k in range(2):
            if k:  # one worker forgets every problem of this CPre, as if it had restarted
                first = pool.problem_key
                lost = client.run(forget, pool.model_key, workers=[sorted(client.nthreads())[0]])
                assert list(lost.values()) == [1]
            Z = random_set(rng, ex, 0.6)
            got = states_vector(m, pool(state_set(m, np.array(ex.states)[Z])), ex)
            np.testing.assert_array_equal(got, ex.cpre(Z).any(axis=1))
        assert pool.calls == 2 and pool.problem_key != first  # on the cluster both times, the problem sent again
    finally:
        pool.close()


def test_a_problem_pushed_out_of_a_workers_memory_is_loaded_again_from_what_was_sent():
    """Three CPres' problems on one worker (jobs sharing a cluster): the worker keeps two loaded
    (``HELD_PROBLEMS``), and the first, pushed out, is loaded again from the bytes it was sent, with the same
    relations; one never sent is ``ProblemMissing``."""
    rng = np.random.default_rng(7600)
    games = [build(random_net(rng, True), "shared_top") for _ in range(3)]
    keys = [f"test-sent-{k}" for k in range(3)]
    try:
        for key, game in zip(keys, games):
            receive(key, pack(Problem.of(game), key))
            held(key)
        assert HELD_PROBLEMS == 2 and keys[0] not in _HELD and all(k in _HELD for k in keys[1:])
        problem, game = held(keys[0]), games[0]
        assert len(problem.chain) == len(game.chain)
        for (rel, _), (want, _) in zip(problem.chain, game.chain):  # the same relations, in the worker's own manager
            assert from_bytes(game.model, to_bytes(problem.model, rel)) == want
        with pytest.raises(ProblemMissing, match="not sent"):
            held("test-sent-never")
    finally:
        for key in keys:
            forget(key)


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
    game.processes, game.parallel_after, game.partitioned = 2, 0.0, lambda cpre, parts: pool
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
                                 SynthesisOptions(reach_and_stay_methods=("reach_safe",)))
    want = results["reach_safe"].domain_states
    assert want == 191_493  # tests/test_pinned_numbers.py
    for per_worker in (1, 3):
        game, got, report = synthesize(a.network, a.relations, a.interconnection, spec.specification,
                                       SynthesisOptions(reach_and_stay_methods=("reach_safe",), processes="auto",
                                                        auto_parts=parts_for(client, per_worker), parallel_after=0.0),
                                       partitioned=on_cluster(client))
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
                                 controller="reach_safe", synthesis_engine="cudd"))
    report = run_job(spec, tmp_path / "job", execution=Execution(client=client))
    assert report["domain_states"] == 191_493
    assert report["synthesis"]["parallel"]["on"] == "cluster"
    assert report["synthesis"]["parallel"]["calls"] > 0
    assert client.status == "running"  # a caller's client stays open


def test_where_synthesis_runs_follows_the_options(client):
    """With CUDD (the oxidd default: tests/test_engine_cpre.py)."""
    spec = parse_spec(_consensus(3, synthesis_engine="cudd"))
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
