"""Synthesis reports as it goes: one progress event per fixed-point iteration, in order, with the size of the
iterate, and the same results as without a callback."""

from __future__ import annotations

import numpy as np
import pytest

from pipelines.spec.model import parse_spec
from pipelines.symbolic.relations import state_set
from pipelines.synthesis.fixed_points import cobuchi, reach, reach_and_stay, reach_safe, safe

from .games import Explicit, build, cells, integrator_spec, integrators, random_net, random_set


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
    """``("synthesis", 0, 1)`` first, then ``(k, k + 1)`` for k = 1, 2, ... (one per message: the construction of the
    BDDs, then one per iteration of every fixed point, never done), then ``(1, 1)``; the count of iteration events is
    the iterations the report gives."""
    from workers.control import run_synthesis
    from workers.job import run_abstraction

    specification = {"kind": kind, "target": {"boxes": [{"lb": 2.5, "ub": 5.5}]}}
    spec = parse_spec(integrator_spec(specification, closed_loop_runs=0))
    events: list[tuple[str, int, int, str]] = []
    report = run_synthesis(run_abstraction(spec, audit=False), None,
                           progress=lambda stage, done, total, message: events.append((stage, done, total, message)))
    syn = [e for e in events if e[0] == "synthesis"]
    assert syn[0][1:3] == (0, 1) and syn[-1][1:3] == (1, 1)
    middle = syn[1:-1]
    assert [(done, total) for _, done, total, _ in middle] == [(k, k + 1) for k in range(1, len(middle) + 1)]
    results = report["synthesis"]["results"]
    rounds = sum(r.get("local_games", {}).get("rounds", 0) for r in results.values())
    assert rounds == (kind == "reach_and_stay")  # the safety part's local games: one round, one event
    iterations = [e for e in middle if not e[3].startswith("building the relation")]  # the BDDs' construction first
    assert len(iterations) == sum(r["iterations"] + r["inner_iterations"] for r in results.values()) + rounds > 2
    games = [message for *_, message in middle if " local games round " in message]
    assert len(games) == rounds and all(m.startswith("reach_safe/safe local games round ") for m in games)
    assert all(message.split(" iteration")[0] in {"reach", "cobuchi", "reach_safe/safe", "reach_safe/reach"}
               and message.endswith(" states") for *_, message in iterations if message not in games)


def test_large_iterates_are_reported_by_their_nodes(monkeypatch):
    """Above PROGRESS_COUNT_NODES an iterate is reported by its BDD nodes (an exact count would walk it in
    Python); below, by its exact number of states."""
    import pipelines.synthesis.fixed_points as fp

    game = _line()
    T = state_set(game.model, np.array([[0]]))
    monkeypatch.setattr(fp, "PROGRESS_COUNT_NODES", 0)
    seen = Recorder()
    reach(game, T, layered=True, progress=seen)
    assert seen.events and all(m.endswith(" BDD nodes") for _, m in seen.events)
    monkeypatch.undo()
    seen = Recorder()
    reach(game, T, layered=True, progress=seen)
    assert all(m.endswith(" states") for _, m in seen.events)


CRASH_CASE = """
import sys, yaml
from pipelines.spec.model import parse_spec
from pipelines.synthesis.options import SynthesisOptions
from pipelines.synthesis.synthesize import synthesize
from workers.job import run_abstraction
from workers.processes.partitioned_cpre import PartitionedPredecessors

def main():
    data = yaml.safe_load(open(sys.argv[1]).read())
    data["parameters"]["N"] = 6
    data["options"]["initial_states"] = []
    spec = parse_spec(yaml.safe_dump(data))
    a = run_abstraction(spec, audit=False)
    events = []
    _, results, _ = synthesize(a.network, a.relations, a.interconnection, spec.specification,
                               SynthesisOptions(reach_and_stay_methods=("reach_safe",), processes=2, parallel_after=0.0),
                               partitioned=PartitionedPredecessors,
                               progress=lambda k, m: events.append(m) if not m.startswith("building the relation") else None)
    print("domain", results["reach_safe"].domain_states, "events", len(events))

if __name__ == "__main__":
    main()
"""


@pytest.mark.slow
def test_progress_of_a_partitioned_fixed_point_does_not_abort_cudd(tmp_path):
    """Consensus N = 6 with its parts in helper processes and a progress callback, in a child process (CUDD aborts
    the whole process): CUDD's own model count per iteration aborted it ("cuddGarbageCollect: problem in
    constants") in the fourth reach iteration; it must finish with the one-process domain."""
    import subprocess
    import sys

    from .conftest import EXAMPLES

    script = tmp_path / "case.py"
    script.write_text(CRASH_CASE)
    done = subprocess.run([sys.executable, str(script), str(EXAMPLES / "consensus.yaml")], capture_output=True,
                          text=True, timeout=600, cwd=str(EXAMPLES.parent))
    assert done.returncode == 0, done.stderr[-2000:]
    assert "domain 51048559 events 10" in done.stdout, done.stdout


def test_building_the_relations_reports_as_it_goes(monkeypatch):
    """Before its first iteration, BDD synthesis says which relation it builds and, now and then, how far it is
    (leaves, tree levels); the events are iteration 0 and the results are those of a silent run."""
    import yaml

    import pipelines.symbolic.tree as tree_module
    from pipelines.network import build_network
    from pipelines.synthesis.options import SynthesisOptions
    from pipelines.synthesis.synthesize import synthesize
    from workers.job import run_abstraction

    from .conftest import EXAMPLES

    data = yaml.safe_load((EXAMPLES / "dcdc.yaml").read_text())
    data["subsystems"][0]["state"]["eta"] = 0.01
    data["options"] = {"audit_transitions": 0}
    spec = parse_spec(data)
    ab = run_abstraction(spec, audit=False)
    monkeypatch.setattr(tree_module, "SAY_EVERY", 0.0)
    seen = Recorder()
    cpre, results, _ = synthesize(build_network(spec), ab.relations, ab.interconnection, spec.specification,
                                  SynthesisOptions(), progress=seen)
    cpre2, silent, _ = synthesize(build_network(spec), ab.relations, ab.interconnection, spec.specification,
                                  SynthesisOptions())
    builds = [m for k, m in seen.events if k == 0 and m.startswith("building the relation of subsystem 0")]
    assert builds[0].endswith(f"({ab.relations[next(iter(ab.relations))].blocking.size:,} boxes)")
    assert any("leaves" in m for m in builds) and any("tree level" in m for m in builds)
    assert results["safe"].domain_states == silent["safe"].domain_states
