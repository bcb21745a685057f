"""workers.dispatch: parts handed out as workers free up (issue 24), simulated with drawn durations."""

from __future__ import annotations

import heapq

import numpy as np
import pytest

from workers.dispatch import Dispatch, Task


def simulate(d: Dispatch, seconds: dict[tuple[str, int], float]) -> tuple[list[tuple[float, float, Task]], float]:
    """Run ``d`` against tasks that take ``seconds[(kind, k)]``; check after every event that no slot idles while
    a task could run there. Returns the tasks' (start, end, task) and the makespan."""
    clock, events, runs = 0.0, [], []
    n = 0

    def launch(tasks: list[Task]) -> None:
        nonlocal n
        for t in tasks:
            end = clock + seconds[(t.kind, t.k)]
            heapq.heappush(events, (end, n, t))
            runs.append((clock, end, t))
            n += 1

    launch(d.start())
    while events:
        clock, _, t = heapq.heappop(events)
        launch(d.done(t))
        # work-conserving: a free slot and a task that could start never coexist
        if d._free:
            assert not d._first and not d._ready(), "a worker idles while a part waits"
    assert d.finished
    return runs, clock


@pytest.mark.parametrize("parts,slots", [(16, 16), (32, 16), (48, 16), (6, 2), (5, 3), (3, 8)])
def test_one_phase_parts_each_run_once_one_per_worker_at_a_time_largest_first(parts, slots):
    rng = np.random.default_rng(parts * 100 + slots)
    work = rng.uniform(0.2, 3.0, parts)
    d = Dispatch(work, slots)
    first = d.start()
    assert len(first) == min(parts, slots) and {t.slot for t in first} == set(range(min(parts, slots)))
    assert [t.k for t in first] == list(np.argsort(-work, kind="stable")[:len(first)])  # largest first
    d2 = Dispatch(work, slots)
    actual = {("part", k): float(w * rng.uniform(0.5, 1.6)) for k, w in enumerate(work)}  # the estimate is off
    runs, makespan = simulate(d2, actual)
    assert sorted(t.k for _, _, t in runs) == list(range(parts)) and all(t.kind == "part" for _, _, t in runs)
    assert d2.most_in_flight == min(parts, slots)
    for s in range(slots):  # one task at a time per worker
        spans = sorted((a, b) for a, b, t in runs if t.slot == s)
        assert all(b1 <= a2 for (_, b1), (a2, _) in zip(spans, spans[1:]))
    # list scheduling: the last worker ends within one part of the mean load
    total = sum(actual.values())
    assert makespan <= total / min(parts, slots) + max(actual.values()) + 1e-9


def test_joins_wait_for_every_first_phase_they_read_and_go_where_their_own_pairs_are_kept():
    rng = np.random.default_rng(7)
    parts, slots = 12, 4
    work = rng.uniform(0.5, 2.0, parts)
    needs = [[k, *(j for j in (k - 1, k + 1, k + 2) if 0 <= j < parts)] for k in range(parts)]
    d = Dispatch(work, slots, needs)
    seconds = {("core", k): float(rng.uniform(0.5, 2.0)) for k in range(parts)}
    seconds |= {("join", k): float(rng.uniform(0.1, 0.5)) for k in range(parts)}
    runs, _ = simulate(d, seconds)
    core_end = {t.k: b for _, b, t in runs if t.kind == "core"}
    core_slot = {t.k: t.slot for _, _, t in runs if t.kind == "core"}
    joins = [(a, t) for a, _, t in runs if t.kind == "join"]
    assert sorted(core_end) == sorted(t.k for _, t in joins) == list(range(parts))
    for a, t in joins:
        assert all(core_end[j] <= a for j in needs[t.k]), f"join {t.k} began before a first phase it reads ended"
    # every first phase before any join (largest first), and most joins where their own range's pairs are kept
    assert max(a for a, _, t in runs if t.kind == "core") <= min(a for a, _ in joins)
    assert sum(core_slot[t.k] == t.slot for _, t in joins) >= parts // 2


def test_a_join_is_not_held_back_for_its_own_worker_while_another_idles():
    # three ranges on two workers: first phases first, then each join where its own pairs are kept if that is free
    d = Dispatch([2.0, 1.0, 1.0], 2, [[0], [1, 2], [2]])
    assert d.start() == [Task("core", 0, 0), Task("core", 1, 1)]
    assert d.done(Task("core", 1, 1)) == [Task("core", 2, 1)]  # a first phase before any join
    # joins 1 and 2 are ready, both kept on worker 1: one of them there, the other waits (worker 0 is busy)
    assert d.done(Task("core", 2, 1)) == [Task("join", 1, 1)]
    assert d.done(Task("core", 0, 0)) == [Task("join", 0, 0)]
    assert d.done(Task("join", 1, 1)) == [Task("join", 2, 1)]
    d = Dispatch([2.0, 1.0, 1.0], 2, [[0], [1], [2]])
    d.start()
    d.done(Task("core", 1, 1))
    assert d.done(Task("core", 0, 0)) == [Task("join", 0, 0)]
    # slot 0 frees while join 1's own slot runs core 2: join 1 runs on slot 0 rather than wait
    assert d.done(Task("join", 0, 0)) == [Task("join", 1, 0)]
    assert not d.finished
    d.done(Task("join", 1, 0))
    assert d.done(Task("core", 2, 1)) == [Task("join", 2, 1)]
    d.done(Task("join", 2, 1))
    assert d.finished


def test_with_a_range_per_worker_the_joins_go_with_the_first_phases_to_their_own_workers():
    # Dask starts each join once the first phases it depends on ended, without a round trip through the job
    d = Dispatch([2.0, 1.0, 1.5], 3, [[0, 1], [1, 2], [2]])
    assert d.at_once
    assert d.start() == [Task("core", 0, 0), Task("core", 2, 1), Task("core", 1, 2),
                         Task("join", 0, 0), Task("join", 1, 2), Task("join", 2, 1)]
    assert d.most_in_flight == 3  # a join runs after its own range's first phase, on the same worker
    assert d.done(Task("core", 2, 1)) == []  # first phases' ends may be reported, or not
    for k, slot in ((0, 0), (1, 2)):
        assert d.done(Task("join", k, slot)) == [] and not d.finished
    assert d.done(Task("join", 2, 1)) == []
    assert d.finished and d.most_in_flight == 3
    assert not Dispatch([1.0] * 4, 3, [[k] for k in range(4)]).at_once  # more ranges than workers: handed out
    assert not Dispatch([1.0] * 2, 3).at_once  # one phase: nothing to wait for


def test_dispatch_needs_a_slot():
    with pytest.raises(ValueError, match="at least one slot"):
        Dispatch([1.0], 0)
