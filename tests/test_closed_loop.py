"""Controllers refined to the concrete system: files, `load_controller(DIR).inputs(x)`, `compabs simulate`,
and closed-loop runs of the concrete black boxes that satisfy each kind of specification."""

import json

import numpy as np
import pytest
import yaml

from pipelines.controller_loading import load_controller
from pipelines.network import build_network
from pipelines.spec.model import parse_spec
from pipelines.verification.closed_loop import simulate, simulate_many
from service.cli import main
from workers.control import run_synthesis
from workers.job import run_abstraction

from .conftest import EXAMPLES


def _small(kind="reach_and_stay", **spec_updates):
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["options"]["audit_transitions"] = 20_000
    data["options"]["closed_loop_runs"] = 40
    if kind == "reach":
        data["specification"] = {"kind": "reach", "target": {"boxes": [{"lb": 4.5, "ub": 9.5}]}}
    elif kind == "safe":
        data["specification"] = {"kind": "safe", "safe": {"boxes": [{"lb": 0, "ub": 14.5}]}}
    elif kind == "reach_avoid":
        data["specification"] = {"kind": "reach_avoid", "target": {"boxes": [{"lb": 20.5, "ub": 25.5}]},
                                 "avoid": {"boxes": [{"lb": [0, 0], "ub": [3, 32]}]}}
    data.update(spec_updates)
    return parse_spec(data)


@pytest.fixture(scope="module")
def small_job(tmp_path_factory):
    out = tmp_path_factory.mktemp("small")
    spec = _small()
    result = run_abstraction(spec)
    report = run_synthesis(result, out)
    return out, spec, report


@pytest.mark.parametrize("kind", ["reach", "safe", "reach_avoid", "reach_and_stay"])
def test_each_specification_holds_in_closed_loop(tmp_path, kind):
    spec = _small(kind)
    report = run_synthesis(run_abstraction(spec), tmp_path)
    assert report["domain_states"] > 0
    closed = report["closed_loop"]
    assert closed["runs"] >= 40
    assert closed["violations"] == 0, closed["first_violation"]
    if kind in ("reach", "reach_avoid"):
        assert closed["steps_to_reach"]["max"] <= closed["steps"]


def test_load_controller_gives_admissible_concrete_inputs(small_job):
    out, spec, report = small_job
    c = load_controller(out)
    net = build_network(spec, None)
    rng = np.random.default_rng(0)
    checked = 0
    for x in rng.uniform(0, 32, (300, 2)):
        u = c.inputs(x)
        assert u.ndim == 2 and u.shape[1] == 2
        idx = c.cell(x)
        assert (u.shape[0] > 0) == bool(c.in_domain(idx[None, :])[0])
        for row in u:  # every input is a grid point of the input set
            assert np.all(np.isin(row, net.subsystems[0].input_grid.axis_points(0)))
        checked += u.shape[0] > 0
    assert checked > 50
    assert c.inputs(np.array([40.0, 1.0])).shape == (0, 2)  # outside the state set: empty


def test_a_loaded_controller_drives_the_concrete_system(small_job):
    out, spec, report = small_job
    c = load_controller(out)
    net = build_network(spec, None)
    x0 = np.array(spec.options.initial_states[0])
    from pipelines.spec.regions import spec_regions

    target = spec_regions(spec, net)["target"]
    run = simulate(net, c.inputs, x0, 60, np.random.default_rng(3), "reach_and_stay", target=target)
    assert run.violation is None
    free = simulate(net, None, x0, 60, np.random.default_rng(3), "reach_and_stay")
    # Without the controller the agents split to the two stable equilibria (the paper's bimodality).
    assert abs(free.states[-1, 0] - free.states[-1, 1]) > 20
    assert abs(run.states[-1, 0] - run.states[-1, 1]) <= 5


@pytest.mark.parametrize("kind", ["reach_and_stay", "reach", "safe"])
def test_runs_in_lockstep_are_the_runs_one_at_a_time(small_job, kind):
    """``simulate_many`` is ``simulate`` per row (deterministic input choice), including runs that stop early:
    states outside the box or the domain, targets reached (reach), the safe set left."""
    out, spec, _ = small_job
    c = load_controller(out)
    net = build_network(spec, None)
    from pipelines.spec.regions import spec_regions

    target = spec_regions(spec, net)["target"]
    rng = np.random.default_rng(7)
    X0 = np.vstack([rng.uniform(0, 32, (25, 2)), [[40.0, 1.0]], spec.options.initial_states])
    calls = []
    many = simulate_many(net, c, X0, 30, np.random.default_rng(0), kind, target=target, choose="first",
                         progress=lambda k, n: calls.append((k, n)))
    assert len(many) == X0.shape[0]
    assert calls[-1] == (30, 30) and [k for k, _ in calls] == sorted(k for k, _ in calls)  # ends at 1.0
    stopped = 0
    for x0, run in zip(X0, many):
        one = simulate(net, c, x0, 30, np.random.default_rng(0), kind, target=target, choose="first")
        np.testing.assert_array_equal(run.states, one.states)
        np.testing.assert_array_equal(run.inputs, one.inputs)
        np.testing.assert_array_equal(run.in_target, one.in_target)
        assert (run.violation, run.settled_at) == (one.violation, one.settled_at)
        stopped += run.inputs.shape[0] < 30
    assert stopped > 0  # some runs ended early, so the bookkeeping of finished runs was exercised


@pytest.mark.parametrize("choose", ["random", "first", "steady"])
def test_simulate_command(small_job, capsys, choose):
    out, spec, _ = small_job
    x0 = ",".join(str(v) for v in spec.options.initial_states[0])
    assert main(["simulate", str(out), "--x0", x0, "--steps", "20", "--choose", choose]) == 0
    run = json.loads(capsys.readouterr().out)
    assert len(run["states"]) == 21 and run["violation"] is None and run["in_target"][-1]


@pytest.mark.parametrize("x0,match", [("1,2,3", "3 components"), ("a,b", "comma-separated numbers")])
def test_simulate_rejects_bad_initial_states(small_job, capsys, x0, match):
    out, _, _ = small_job
    assert main(["simulate", str(out), "--x0", x0]) == 2
    assert match in capsys.readouterr().err


def test_simulate_without_a_controller(tmp_path, capsys):
    assert main(["simulate", str(tmp_path), "--x0", "1,2"]) == 2
    assert "no controller" in capsys.readouterr().err


def test_domain_sampling_stays_in_the_domain_and_spreads(small_job):
    out, _, report = small_job
    c = load_controller(out)
    cells = c.sample_cells(300, np.random.default_rng(0))
    assert cells.shape == (300, 2)
    assert c.in_domain(cells).all()
    # uniform over 629 domain cells: 300 draws hit well over 150 distinct cells
    assert len({tuple(r) for r in cells}) > 150
