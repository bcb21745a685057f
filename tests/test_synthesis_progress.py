"""Synthesis reports as it goes: one progress event per fixed-point iteration, in order, with the size of the
iterate, and the same results as without a callback."""

from __future__ import annotations

import numpy as np
import pytest

from pipelines.spec.model import parse_spec
from pipelines.symbolic.relations import state_set
from pipelines.synthesis.fixed_points import cobuchi, reach, reach_and_stay, reach_safe, safe

from .test_spec_kinds import _integrator_spec, cells, integrators
from .test_synthesis import Explicit, build, random_net, random_set


def _line(K: int = 10):
    return build(integrators((K,)), "interleaved")


class Recorder:
    def __init__(self) -> None:
        self.events: list[tuple[int, str]] = []

    def __call__(self, iteration: int, message: str) -> None:
        self.events.append((iteration, message))


@pytest.mark.parametrize("layered", [False, True], ids=["explicit", "layered"])
def test_reach_emits_one_event_per_iteration_with_the_attractor_size(layered):
    """On the line 0..9 towards T = {9} the attractor grows by one cell per iteration (by hand): 2, 3, ..., 10,
    and the last iteration, which finds nothing new, says 10 again."""
    game = _line()
    seen = Recorder()
    res = reach(game, cells(game, 9), layered=layered, progress=seen)
    assert res.iterations == 10
    assert seen.events == [(k, f"reach iteration {k}: {min(k + 1, 10):,} states") for k in range(1, 11)]


def test_safe_and_reach_safe_emit_their_iterations_in_order():
    game = _line()
    seen = Recorder()
    res = safe(game, cells(game, *range(2, 8)), progress=seen)
    assert [k for k, _ in seen.events] == list(range(1, res.iterations + 1))
    assert seen.events[-1][1] == f"safe iteration {res.iterations}: {res.domain_states:,} states"

    seen = Recorder()
    res = reach_safe(game, cells(game, 4, 5, 6), progress=seen)
    parts = [message.split(" iteration")[0] for _, message in seen.events]
    n_safe = res.inner_iterations  # Reach(Safe): the safety part's iterations are the inner ones
    assert parts == ["reach_safe/safe"] * n_safe + ["reach_safe/reach"] * res.iterations
    assert [k for k, _ in seen.events] == list(range(1, n_safe + 1)) + list(range(1, res.iterations + 1))
    assert seen.events[-1][1].endswith(f": {res.domain_states:,} states")


@pytest.mark.parametrize("seed", range(6))
def test_cobuchi_emits_every_inner_and_outer_iteration_and_results_do_not_change(seed):
    """Inner ν iterations and outer μ iterations each count up by one, an outer event after its inner ones; the
    fixed points with a callback return the very BDDs they return without one."""
    rng = np.random.default_rng(600 + seed)
    net = random_net(rng, bool(seed % 2))
    game = build(net, "interleaved")
    ex = Explicit(net)
    phi = state_set(game.model, np.array(ex.states)[random_set(rng, ex, 0.6)])
    seen = Recorder()
    res = cobuchi(game, phi, progress=seen)
    assert len(seen.events) == res.iterations + res.inner_iterations
    outer = [k for k, message in seen.events if ", inner" not in message]
    inner = [k for k, message in seen.events if ", inner" in message]
    assert outer == list(range(1, res.iterations + 1)) and inner == list(range(1, res.inner_iterations + 1))
    assert ", inner" not in seen.events[-1][1]
    plain = cobuchi(game, phi)
    assert (res.domain, res.controller) == (plain.domain, plain.controller)
    for name, r in reach_and_stay(game, phi, progress=Recorder()).items():
        q = reach_and_stay(game, phi, (name,))[name]
        assert (r.domain, r.controller) == (q.domain, q.controller), name


def test_an_error_raised_by_the_callback_stops_the_fixed_point():
    """A cancellation raised from ``progress`` reaches the caller (not swallowed, not turned into another error)."""
    game = _line()

    class Cancelled(Exception):
        pass

    def cancel_at_three(iteration: int, message: str) -> None:
        if iteration == 3:
            raise Cancelled(message)

    with pytest.raises(Cancelled, match="reach iteration 3: 4 states"):
        reach(game, cells(game, 9), progress=cancel_at_three)


@pytest.mark.parametrize("kind", ["reach", "reach_and_stay"])
def test_run_synthesis_maps_iterations_to_stage_progress(kind):
    """``("synthesis", 0, 1)`` first, then ``(k, k + 1)`` for k = 1, 2, ... (one per iteration of every fixed point,
    never done), then ``(1, 1)``; the count of iteration events is the iterations the report gives."""
    from workers.control import run_synthesis
    from workers.job import run_abstraction

    specification = {"kind": kind, "target": {"boxes": [{"lb": 2.5, "ub": 5.5}]}}
    spec = parse_spec(_integrator_spec(specification, closed_loop_runs=0))
    events: list[tuple[str, int, int, str]] = []
    report = run_synthesis(run_abstraction(spec, audit=False), None,
                           progress=lambda stage, done, total, message: events.append((stage, done, total, message)))
    syn = [e for e in events if e[0] == "synthesis"]
    assert syn[0][1:3] == (0, 1) and syn[-1][1:3] == (1, 1)
    middle = syn[1:-1]
    assert [(done, total) for _, done, total, _ in middle] == [(k, k + 1) for k in range(1, len(middle) + 1)]
    results = report["synthesis"]["results"]
    assert len(middle) == sum(r["iterations"] + r["inner_iterations"] for r in results.values()) > 2
    assert all(message.split(" iteration")[0] in {"reach", "cobuchi", "reach_safe/safe", "reach_safe/reach"}
               and message.endswith(" states") for *_, message in middle)
