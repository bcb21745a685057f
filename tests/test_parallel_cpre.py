"""The plan of the partitioned ``∃u.CPre`` (pipelines/synthesis/partition.py: cuts, balancing, exact parts), the
policy of :meth:`ControllablePredecessor.predecessors` around it, and its helper processes
(workers/processes/partitioned_cpre.py): started from the caller's package, stopped, and a clear failure when one
dies. Their answers, through either transport, are tested in tests/test_partitioned_cpre.py."""

from __future__ import annotations

import itertools
import os
import weakref

import numpy as np
import pytest

from pipelines.symbolic.relations import state_set
from pipelines.synthesis.cpre import ControllablePredecessor, PartitionFailed, resolve_processes
from pipelines.synthesis.partition import (
    damped_cuts,
    equal_work_cuts,
    lexicographic_part,
    split_digits,
    update_density,
    w_window,
)
from pipelines.synthesis.parts import window_predecessors
from tests.games import Explicit, build, random_net, random_set, states_vector
from workers.processes.partitioned_cpre import HelperError, PartitionedPredecessors


def test_equal_work_cuts_split_the_work_evenly():
    assert equal_work_cuts(np.ones(20), 2) == [10]
    assert equal_work_cuts(np.ones(15), 3) == [5, 10]
    assert equal_work_cuts(np.r_[np.full(10, 0.9), np.full(10, 0.1)], 2) == [6]


def test_equal_work_cuts_keep_every_part_nonempty():
    assert equal_work_cuts(np.array([100.0, 0.0, 0.0]), 3) == [1, 2]
    assert equal_work_cuts(np.array([0.0, 0.0, 100.0]), 3) == [1, 2]
    for seed in range(20):
        rng = np.random.default_rng(seed)
        cells = int(rng.integers(2, 40))
        parts = min(int(rng.integers(2, 5)), cells)
        cuts = equal_work_cuts(rng.random(cells) ** 4, parts)
        assert len(cuts) == parts - 1
        assert all(1 <= c <= cells - 1 for c in cuts)
        assert all(a < b for a, b in zip(cuts, cuts[1:]))


def test_update_density_matches_each_range_to_its_time():
    d = update_density(np.ones(20), [(0, 9), (10, 31)], [9.0, 1.0])  # the last range past the cells
    np.testing.assert_allclose([d[:10].sum(), d[10:].sum()], [9.0, 1.0])
    assert equal_work_cuts(d, 2) == [6]
    # a hot cell moved across the cut: its share is remembered, so the cut settles instead of oscillating
    truth = np.ones(20)
    truth[9] = 5.0
    d, cuts = np.ones(20), [10]
    seen = []
    for _ in range(8):
        bounds = [(0, cuts[0] - 1), (cuts[0], 31)]
        d = update_density(d, bounds, [truth[a:b + 1].sum() for a, b in bounds])
        cuts = damped_cuts(cuts, equal_work_cuts(d, 2))
        seen.append(cuts[0])
    best = min(range(1, 20), key=lambda c: max(truth[:c].sum(), truth[c:].sum()))
    assert seen[-3:] == [best] * 3, seen


@pytest.mark.parametrize("order", ["interleaved", "shared_top"])
def test_lexicographic_parts_partition_every_code(order):
    """Consecutive parts ``[s_0, s_1), ..., [s_k, None)`` hold every code pair of the two digits exactly once
    (codes past the grid included), each the pairs between its start and the next one; one digit likewise."""
    rng = np.random.default_rng(41 if order == "interleaved" else 42)
    m = build(random_net(rng, order == "shared_top"), order).model
    digits = split_digits(m)
    in_order = [v.rsplit("_", 1)[0] for v in m.variables if v.startswith("x") and not v.startswith("xn")]
    assert digits == tuple(dict.fromkeys(in_order))[:2]
    bdd = m.bdd

    def holds(f, codes):
        value = {b: bool((c >> (len(m.bits[d]) - 1 - k)) & 1)
                 for d, c in zip(digits, codes) for k, b in enumerate(m.bits[d])}
        g = bdd.let(value, f)
        assert g in (bdd.true, bdd.false), "a part reads bits outside its digits"
        return g == bdd.true

    for used in (digits, digits[:1]):
        sizes = [m.sizes[d] for d in used]
        every = list(itertools.product(*(range(1 << len(m.bits[d])) for d in used)))
        for _ in range(15):
            cells = list(itertools.product(*(range(k) for k in sizes)))
            k = int(rng.integers(1, min(4, len(cells))))
            starts = [(0,) * len(used)] + sorted(cells[i] for i in rng.choice(np.arange(1, len(cells)), k, replace=False))
            parts = [lexicographic_part(m, used, a, b) for a, b in zip(starts, [*starts[1:], None])]
            for codes in every:
                padded = (*codes, *([0] * (len(digits) - len(used))))
                owners = [j for j, f in enumerate(parts) if holds(f, padded)]
                assert owners == [sum(s <= codes for s in starts) - 1], (starts, codes, owners)


@pytest.mark.parametrize("seed", range(4))
def test_w_windows_partition_the_states_and_their_parts_are_the_predecessors(seed):
    """Windows of the shared ``ŵ`` at random cuts: their states are disjoint and cover every state with an
    admissible ``ŵ``, each window holds every ``ŵ`` its states admit, and the parts of
    :func:`window_predecessors` are the explicit ``∃u.CPre(Z)`` on their states (whole, ``within``, ``outside``)."""
    rng = np.random.default_rng(8100 + seed)
    net = random_net(rng, True)
    ex = Explicit(net)
    game = build(net, "shared_top")
    m, bdd, M = game.model, game.bdd, game.M
    (digit,) = m.w_digits()
    assert M is not None
    some_w = bdd.exist(m.w_bits, M)
    for _ in range(4):
        k = int(rng.integers(1, m.sizes[digit]))
        starts = [0, *sorted(rng.choice(np.arange(1, m.sizes[digit]), size=k - 1, replace=False).tolist())]
        windows = [w_window(m, M, digit, a, b) for a, b in zip(starts, [*starts[1:], None])]
        union = bdd.false
        for (states, window), a in zip(windows, starts):
            assert (union & states) == bdd.false  # disjoint
            union |= states
            assert (states & M & ~window) == bdd.false  # every admitted ŵ is in the window
            assert (window & m.interval(digit, 0, a - 1)) == bdd.false or a == 0  # nothing below the range
        assert union == some_w
        Z, S, Out = random_set(rng, ex, 0.6), random_set(rng, ex, 0.7), random_set(rng, ex, 0.5)
        bZ, bS, bO = (state_set(m, np.array(ex.states)[v]) for v in (Z, S, Out))
        want = ex.cpre(Z).any(axis=1)
        inside = game.within(bS)
        for chain, admissible, outside, expect, on in (
                (game.chain, game.admissible, None, want, slice(None)),
                (inside.chain, inside.admissible, None, want & S, slice(None)),
                (game.chain, game.admissible, bO, want, Out)):
            got = bdd.false
            for states, window in windows:
                part = window_predecessors(m, chain, admissible, M, m.w_bits, m.u_bits, bZ, states, window, outside)
                assert (part & ~states) == bdd.false
                got |= part
            np.testing.assert_array_equal(states_vector(m, got, ex)[on], expect[on])


def test_damped_cuts_move_half_way_and_stay_ordered():
    assert damped_cuts([16], [16]) == [16]
    assert damped_cuts([16], [18]) == [17] and damped_cuts([18], [15]) == [17] and damped_cuts([4], [12]) == [8]
    rng = np.random.default_rng(5)
    for _ in range(2000):
        cells, parts = int(rng.integers(3, 40)), int(rng.integers(2, 6))
        if parts > cells:
            continue
        old = equal_work_cuts(rng.exponential(size=cells), parts)
        target = equal_work_cuts(rng.exponential(size=cells), parts)
        new = damped_cuts(old, target)
        assert all(a < b for a, b in zip(new, new[1:])) and 1 <= new[0] and new[-1] <= cells - 1, (old, target, new)
        assert all(min(o, t) <= c <= max(o, t) for o, t, c in zip(old, target, new))


class Made(list):
    """A ``partitioned`` factory that keeps what it made (a test's view of the parts a game started)."""

    def __init__(self, make):
        super().__init__()
        self.make = make

    def __call__(self, cpre, processes):
        self.append(self.make(cpre, processes))
        return self[-1]


def test_close_stops_the_helpers():
    game = build(random_net(np.random.default_rng(5), True), "shared_top")
    pool = PartitionedPredecessors(game, 2)
    pool(game.model.x_domain)
    procs = pool.helpers
    assert all(p.poll() is None for p in procs)
    pool.close()
    pool.close()  # idempotent
    assert all(p.poll() is not None for p in procs)


def test_helpers_import_the_callers_package_from_any_working_directory(tmp_path, monkeypatch):
    """``python -m`` puts its working directory first on sys.path: a caller sitting in a directory with another
    ``pipelines`` package (an older checkout) must still give its helpers its own."""
    (tmp_path / "pipelines").mkdir()
    (tmp_path / "pipelines" / "__init__.py").write_text("raise ImportError('the decoy pipelines package')\n")
    monkeypatch.chdir(tmp_path)
    rng = np.random.default_rng(8)
    net = random_net(rng, True)
    ex = Explicit(net)
    game = build(net, "shared_top")
    pool = PartitionedPredecessors(game, 2)
    try:
        Z = random_set(rng, ex, 0.6)
        got = states_vector(game.model, pool(state_set(game.model, np.array(ex.states)[Z])), ex)
        np.testing.assert_array_equal(got, ex.cpre(Z).any(axis=1))
    finally:
        pool.close()


def test_a_helper_that_dies_is_a_clear_error():
    game = build(random_net(np.random.default_rng(6), False), "interleaved")
    pool = PartitionedPredecessors(game, 3)
    try:
        pool(game.model.x_domain)
        pool.helpers[0].kill()
        pool.helpers[0].wait()
        with pytest.raises(HelperError, match=r"synthesis helper 1 (died|is gone).*synthesis_processes"):
            pool(game.model.x_domain)
        assert all(p.poll() is not None for p in pool.helpers)  # the error stopped the other helper too
    finally:
        pool.close()


def test_after_a_helper_dies_the_game_answers_in_one_process():
    """The call whose helper died is recomputed here (same answer), later calls too, and the report says why."""
    rng = np.random.default_rng(8)
    net = random_net(rng, True)
    ex = Explicit(net)
    game = build(net, "shared_top")
    made = Made(PartitionedPredecessors)
    game.processes, game.parallel_after, game.partitioned = 2, 0.0, made
    m = game.model
    bZ = state_set(m, np.array(ex.states)[random_set(rng, ex, 0.6)])
    want = game.predecessors(bZ)  # in parts from the first call on
    assert len(made) == 1 and game.parallel["calls"] == 1 and game.parallel["on"] == "processes"
    made[0].helpers[0].kill()
    made[0].helpers[0].wait()
    assert game.predecessors(bZ) == want and game.processes == 1
    assert game.predecessors(bZ) == want and len(made) == 1
    assert "synthesis helper 1" in game.parallel["stopped"] and "one process" in game.parallel["stopped"]
    game.close()


def test_without_a_factory_every_call_runs_here():
    game = build(random_net(np.random.default_rng(8), True), "shared_top")
    game.processes, game.parallel_after = 2, 0.0
    want = game.predecessors(game.model.x_domain)
    assert game.predecessors(game.model.x_domain) == want
    assert game.parallel == {}


class _FailingParts:
    """A ``partitioned`` factory's product that answers once, then fails as a dead helper would."""

    takes_symmetry = False

    def __init__(self, cpre, processes):
        # weak, as PartitionedCPre: a cycle through CUDD objects would leave their order to the collector
        self.cpre, self.processes, self.calls, self.closed = weakref.ref(cpre), processes, 0, False

    def __call__(self, Z, outside, within, symmetry=None):
        self.calls += 1
        if self.calls > 1:
            self.close()
            raise PartitionFailed("part 1 died")
        cpre = self.cpre()
        return cpre.predecessors(Z, outside, within, part=cpre.model.x_domain)

    def close(self):
        self.closed = True

    def report(self):
        return {"on": "here", "calls": self.calls}


def test_a_failed_part_is_recomputed_here_and_reported():
    """The policy of :meth:`ControllablePredecessor.predecessors` with an injected factory: started after the
    first call that took ``parallel_after`` seconds (with ``0``, before the first call), used for the next,
    dropped on :class:`PartitionFailed` (same answer), never started again."""
    assert issubclass(HelperError, PartitionFailed)
    game = build(random_net(np.random.default_rng(8), True), "shared_top")
    made = Made(_FailingParts)
    game.processes, game.parallel_after, game.partitioned = 3, 1e-9, made
    Z = game.model.x_domain
    want = game.predecessors(Z)
    assert len(made) == 1 and made[0].processes == 3 and made[0].calls == 0
    parts = made[0]
    assert game.predecessors(Z) == want and parts.calls == 1
    assert game.predecessors(Z) == want and parts.closed and game.processes == 1
    assert game.predecessors(Z) == want and len(made) == 1 and parts.calls == 2
    assert game.parallel["calls"] == 2 and game.parallel["stopped"].startswith("part 1 died")
    first = build(random_net(np.random.default_rng(8), True), "shared_top")
    made = Made(_FailingParts)
    first.processes, first.parallel_after, first.partitioned = 3, 0.0, made
    whole = first.model.x_domain
    want = first.predecessors(whole, part=whole)  # a call on a given part runs here and starts nothing
    assert not made
    assert first.predecessors(whole) == want and len(made) == 1 and made[0].calls == 1


def test_processes_must_be_positive():
    net = random_net(np.random.default_rng(7), False)
    with pytest.raises(ValueError, match="processes must be at least 1"):
        game = build(net, "interleaved")
        ControllablePredecessor(game.model, game.T, game.NB, game.parts, processes=0)
    with pytest.raises(ValueError, match="at least 2 processes"):
        PartitionedPredecessors(build(net, "interleaved"), 1)


def test_resolve_processes():
    assert 1 <= resolve_processes("auto") <= min(4, os.cpu_count() or 1)
    assert resolve_processes(3) == 3
    for bad in (0, -1, True, "two", 1.5):
        with pytest.raises(ValueError, match="processes must be"):
            resolve_processes(bad)


def test_auto_processes_split_only_the_shared_cpre():
    """'auto': one process for the per-subsystem CPre (measured not to pay on the tanks), the CPUs for the
    shared one."""
    for shared, order in ((False, "interleaved"), (True, "shared_top")):
        game = build(random_net(np.random.default_rng(9), shared), order)
        auto = ControllablePredecessor(game.model, game.T, game.NB, game.parts, processes="auto")
        assert auto.method == ("shared" if shared else "per_subsystem")
        assert auto.processes == (resolve_processes("auto") if shared else 1)
