"""``∃u.CPre`` on oxidd (pipelines/synthesis/engine_cpre.py, pipelines/symbolic/oxidd_mirror.py): functions cross
between CUDD and oxidd unchanged, every call and every fixed point gives CUDD's sets (every CPre method, with and
without the symmetry), a failure of the other engine leaves the answers to CUDD, and a job's options choose the
engine."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from pipelines.errors import SpecError
from pipelines.spec.model import parse_spec
from pipelines.symbolic.files import check_dddmp
from pipelines.synthesis.cpre import PartitionFailed
from pipelines.synthesis.fixed_points import reach_safe, safe
from tests.games import Explicit, build, random_net, random_set, ring_net
from tests.test_symmetry import _consensus, _random_set

oxidd_mirror = pytest.importorskip("pipelines.symbolic.oxidd_mirror")
if not oxidd_mirror.oxidd_available():
    pytest.skip("oxidd is not installed", allow_module_level=True)

from pipelines.symbolic.oxidd_mirror import OxiddMirror, cudd_dddmp  # noqa: E402
from pipelines.synthesis.engine_cpre import OnOxidd, OxiddPredecessors, resolve_engine  # noqa: E402

from .conftest import EXAMPLES  # noqa: E402


def _same(plain, game):
    """``same(f, g)``: ``f`` of ``game``'s manager and ``g`` of ``plain``'s are the same set (through DDDMP: the two
    models declare the same variables in the same order)."""
    from pipelines.symbolic.files import from_bytes, to_bytes

    def same(f, g):
        assert f == from_bytes(game.model, to_bytes(plain.model, g))

    return same


def _on_oxidd(game, threads: int = 2):
    """``game`` with every whole ``∃u.CPre`` call on oxidd (as a job's engine sets it), from the first on."""
    game.partitioned, game.parallel_after = OnOxidd(threads, cache=1 << 16), 0.0
    return game


def _states(games, ex, rng, p):
    """One random set of states, in each game's manager."""
    from pipelines.symbolic.relations import state_set

    keep = np.array(ex.states)[random_set(rng, ex, p)]
    return [state_set(g.model, keep) for g in games]


@pytest.mark.parametrize("seed", range(6))
def test_functions_cross_between_cudd_and_oxidd_unchanged(seed, tmp_path):
    """Random sets of states and of state-input pairs, their complements and the constants go to oxidd and back
    equal; what :func:`cudd_dddmp` writes passes the check CUDD's files pass."""
    rng = np.random.default_rng(seed)
    game = build(random_net(rng, bool(seed % 2)), "shared_top" if seed % 2 else "interleaved")
    m = game.model
    mirror = OxiddMirror(m, threads=1, cache=1 << 16)
    try:
        fs = [_random_set(game, rng, 0.5) for _ in range(3)] + [game.admissible, game.bdd.true, game.bdd.false]
        fs += [~f for f in fs[:4]] + [m.var(m.x_bits[0]), ~m.var(m.x_bits[-1])]
        for f in fs:
            g = mirror.put(f)
            assert mirror.get(g) == f
            assert mirror.get(~g) == ~f  # complemented roots and edges, both ways
        g = mirror.put(fs[0] & ~fs[1])
        mirror.write(g, tmp_path / "oxidd.dddmp")
        (tmp_path / "cudd.dddmp").write_bytes(cudd_dddmp((tmp_path / "oxidd.dddmp").read_bytes()))
        check_dddmp(tmp_path / "cudd.dddmp", m.variables)
        assert mirror.to_next(mirror.put(fs[0])) == mirror.put(m.to_next(fs[0]))
    finally:
        mirror.close()


def test_a_file_that_is_not_oxidds_dddmp_is_refused():
    for bad in (b"", b"hello", b".ver DDDMP-2.0\n.nodes\n1 T 0 0\n", b".ver DDDMP-2.0\n.suppvarnames a\n.nodes\n1 2 3\n.end"):
        with pytest.raises(ValueError):
            cudd_dddmp(bad)


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("kind", ["shared", "per_subsystem", "ring_chained"])
def test_predecessors_on_oxidd_are_cudds(seed, kind):
    """Random games of each CPre method: whole calls, with ``outside`` and ``within``, on oxidd equal CUDD's."""
    rng = np.random.default_rng(100 * seed + len(kind))
    if kind == "ring_chained":
        net, order, method = ring_net(rng), "interleaved", "chained"
    else:
        net, order, method = random_net(rng, kind == "shared"), "shared_top", "auto"
    ex = Explicit(net)
    plain, game = build(net, order, method), _on_oxidd(build(net, order, method))
    try:
        for _ in range(3):
            (Zp, Z), (Sp, S) = _states((plain, game), ex, rng, 0.6), _states((plain, game), ex, rng, 0.7)
            same = _same(plain, game)
            same(game.predecessors(Z), plain.predecessors(Zp))
            same(game.predecessors(Z, outside=~Z) & ~Z, plain.predecessors(Zp, outside=~Zp) & ~Zp)
            same(game.predecessors(Z, within=game.within(S)), plain.predecessors(Zp, within=plain.within(Sp)))
        assert game.parallel["on"].startswith("oxidd") and game.parallel["calls"] == 9
    finally:
        game.close()
        plain.close()


@pytest.mark.parametrize("at_once_bits", [1, 64])
def test_oxidd_takes_a_large_shared_cpre_at_once_and_the_others_after_a_long_call(at_once_bits, monkeypatch):
    """At once: a shared CPre of at least 2^AT_ONCE_BITS state codes (here every one, or none); the rest after a
    call took parallel_after seconds in CUDD (0 here after the first call)."""
    from pipelines.synthesis import engine_cpre

    monkeypatch.setattr(engine_cpre, "AT_ONCE_BITS", at_once_bits)
    rng = np.random.default_rng(3)
    for shared, method in ((True, "shared"), (False, "per_subsystem")):
        game = build(random_net(rng, shared), "shared_top")
        game.partitioned = OnOxidd(1, cache=1 << 16)
        assert game.method == method
        try:
            game.predecessors(game.model.x_domain)  # a short call: far less than parallel_after
            assert (game._pool is not None) == (shared and at_once_bits == 1)
            game.parallel_after = 0.0
            game.predecessors(game.model.x_domain)
            assert isinstance(game._pool, OxiddPredecessors)
        finally:
            game.close()
    game.parallel_after = 1.0
    assert OnOxidd.starts(game, 1.0) and not OnOxidd.starts(game, 0.5) and not OnOxidd.starts(game, None)


def test_fixed_points_with_the_symmetry_on_oxidd_are_cudds():
    """Consensus N = 3: the orbit representatives and the closing on oxidd; safety and Reach(Safe) domains equal
    CUDD's with the symmetry (and, through it, the plain ones: tests/test_symmetry.py)."""
    plain, phi_p = _consensus(3)
    game, phi = _consensus(3)
    _on_oxidd(game)
    same = _same(plain, game)
    try:
        for f in (safe, reach_safe):
            same(f(game, phi, layered=True).domain, f(plain, phi_p, layered=True).domain)
        report = game.parallel
        assert report["on"] == "oxidd, 2 threads" and report["calls"] > 0
        assert game._invariant._sym is not None  # the calls took the symmetry
    finally:
        game.close()
        plain.close()


def test_a_failing_engine_leaves_the_calls_to_cudd(monkeypatch):
    """An error inside oxidd (here: its relational product raising) is a PartitionFailed that closes it; the call
    and the later ones run in CUDD with the same answers, and the report says why."""
    rng = np.random.default_rng(5)
    net = random_net(rng, True)
    ex = Explicit(net)
    plain, game = build(net, "shared_top"), _on_oxidd(build(net, "shared_top"))
    same = _same(plain, game)
    Zp, Z = _states((plain, game), ex, rng, 0.6)
    same(game.predecessors(Z), plain.predecessors(Zp))
    pool = game._pool
    assert isinstance(pool, OxiddPredecessors)

    def broken(*args, **kw):
        raise MemoryError("oxidd: out of nodes")

    try:
        monkeypatch.setattr(pool.mirror, "and_exists", broken)
        same(game.predecessors(Z), plain.predecessors(Zp))  # the failed call, answered by CUDD
        assert game._pool is None and game.partitioned is None
        assert not hasattr(pool, "mirror")  # closed: oxidd's nodes are freed while the job goes on
        with pytest.raises(PartitionFailed, match="oxidd failed in a CPre"):
            pool(Z)
        assert "out of nodes" in game.parallel["stopped"]
        Zp, Z = _states((plain, game), ex, rng, 0.4)
        same(game.predecessors(Z), plain.predecessors(Zp))
    finally:
        monkeypatch.undo()
        game.close()
        plain.close()


@pytest.mark.parametrize("nodes", [64, 300])
def test_oxidd_out_of_nodes_leaves_the_calls_to_cudd(nodes):
    """A real fault: oxidd with room for too few nodes runs out of memory, when it starts (64: the chain does not
    fit) or in the second call (300); CUDD answers every call, and the report says why."""
    rng = np.random.default_rng(11)
    net = random_net(rng, True)
    ex = Explicit(net)
    plain, game = build(net, "shared_top"), build(net, "shared_top")
    game.partitioned, game.parallel_after = OnOxidd(1, cache=1 << 10, nodes=nodes), 0.0
    same = _same(plain, game)
    try:
        for p in (0.6, 0.3, 0.8):
            Zp, Z = _states((plain, game), ex, rng, p)
            same(game.predecessors(Z), plain.predecessors(Zp))
        assert game.partitioned is None and "out of memory" in game.parallel["stopped"]
    finally:
        game.close()
        plain.close()


def _consensus_options(**options):
    data = yaml.safe_load((EXAMPLES / "consensus.yaml").read_text())
    data["parameters"]["N"] = 3
    data["options"].update(options)
    return parse_spec(yaml.safe_dump(data)).options


def test_the_jobs_options_choose_the_engine():
    from workers.control import partitioning
    from workers.processes.partitioned_cpre import PartitionedPredecessors

    auto = partitioning(_consensus_options())
    assert auto["engine"] == "oxidd" and isinstance(auto["partitioned"], OnOxidd)
    assert auto["partitioned"].threads >= 1
    for options in ({"synthesis_on": "processes"}, {"synthesis_engine": "cudd"}):
        got = partitioning(_consensus_options(**options))
        assert got["engine"] == "cudd" and got["partitioned"] is PartitionedPredecessors
    with pytest.raises(SpecError, match="synthesis_engine 'oxidd' runs the synthesis in the job's process"):
        partitioning(_consensus_options(synthesis_engine="oxidd", synthesis_on="processes"))
    with pytest.raises(SpecError, match="synthesis_engine"):
        _consensus_options(synthesis_engine="sylvan")
    assert resolve_engine("auto") == "oxidd" and resolve_engine("cudd") == "cudd"
    with pytest.raises(ValueError, match="must be one of"):
        resolve_engine("sylvan")


def test_a_job_on_oxidd_reports_it_and_wins_cudds_domain(tmp_path):
    """Consensus N = 3 end to end in process (on oxidd from the first call: its calls are short): the engine the
    report names, and CUDD's domain."""
    from workers.job import run_job

    def spec(**options):
        data = yaml.safe_load((EXAMPLES / "consensus.yaml").read_text())
        data["parameters"]["N"] = 3
        data["options"].update({"fixed_points": ["reach_safe"], "controller": "reach_safe", "closed_loop_runs": 5,
                                "initial_states": [], "audit_transitions": 1000, **options})
        return parse_spec(yaml.safe_dump(data))

    ox = run_job(spec(synthesis_parallel_after=0.0), tmp_path / "oxidd")
    cu = run_job(spec(synthesis_engine="cudd", synthesis_processes=1), tmp_path / "cudd")
    assert ox["synthesis"]["parallel"]["on"].startswith("oxidd")
    assert ox["domain_states"] == cu["domain_states"] > 0
    assert ox["closed_loop"]["violations"] == 0
