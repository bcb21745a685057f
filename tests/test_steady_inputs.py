"""The figures' closed loop keeps its input while it stays admissible (``choose="steady"``) instead of taking the
first admissible one at each step, which chatters between the extreme inputs inside a reach-and-stay target; and
the phase plane never says the initial state is off the drawn slice while drawing it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from pipelines.controller_loading import load_controller
from pipelines.figures import phase_plane
from pipelines.figures.setting import FigureSetting
from pipelines.grid import UniformGrid
from pipelines.network import build_network
from pipelines.spec.model import parse_spec
from pipelines.spec.regions import closed_loop_regions
from pipelines.verification.closed_loop import Run, admits, simulate
from workers import jobdir
from workers.executors import Execution
from workers.job import run_job

from .conftest import EXAMPLES

# A cart pushed by u in {-1, 1} half a cell a step: inside the target both inputs are admissible except at its ends.
SHUTTLE = """
name: shuttle
subsystems:
  - name: cart
    state: {lb: 0, ub: 10, eta: 1}
    input: {lb: -1, ub: 1, eta: 2, origin: 1}
    dynamics: "x[0] + 0.5 * u[0]"
    lipschitz: {x: 1}
    samples: 4
specification: {kind: reach_and_stay, target: {boxes: [{lb: 2.5, ub: 7.5}]}}
options: {audit_transitions: 1000, closed_loop_runs: 2, initial_states: [[5.0]], fixed_points: [reach_safe],
          controller: reach_safe}
"""


@pytest.fixture(scope="module")
def shuttle(tmp_path_factory):
    out = tmp_path_factory.mktemp("shuttle") / "job"
    spec = parse_spec(SHUTTLE)
    report = run_job(spec, out, execution=Execution(in_process=True))
    assert report["domain_states"] > 0
    return spec, out, report


def _switches(run: Run) -> int:
    return int(np.any(np.diff(run.inputs, axis=0) != 0, axis=1).sum())


def test_steady_inputs_do_not_chatter_inside_the_target(shuttle):
    spec, out, _ = shuttle
    network, controller = build_network(spec, None), load_controller(out)
    regions = closed_loop_regions(spec, network)
    runs = {how: simulate(network, controller, np.array([5.0]), 40, np.random.default_rng(0), "reach_and_stay",
                          choose=how, **regions) for how in ("first", "steady")}
    assert all(run.violation is None for run in runs.values())
    assert _switches(runs["first"]) >= 20  # -1, +1, -1, ... at the target's lower end
    assert _switches(runs["steady"]) <= _switches(runs["first"]) // 3
    steady = runs["steady"]
    for k in range(1, steady.inputs.shape[0]):  # an input changes only where the previous one is not admissible
        if not np.array_equal(steady.inputs[k], steady.inputs[k - 1]):
            assert not admits(controller, steady.states[k], steady.inputs[k - 1])


def test_the_figures_draw_steady_runs(shuttle):
    _, out, report = shuttle
    example = json.loads((out / jobdir.EXAMPLE_RUN).read_text())
    assert example["choose"] == "steady" and example["origin"] == "initial"
    inputs = np.asarray(example["controlled"]["inputs"])
    assert int(np.any(np.diff(inputs, axis=0) != 0, axis=1).sum()) <= inputs.shape[0] // 4
    assert "trajectory.png" in report["figures"]


def test_admits_agrees_with_the_listed_inputs_of_a_bdd_controller(tmp_path):
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["options"].update(audit_transitions=0, closed_loop_runs=1)
    spec = parse_spec(data)
    run_job(spec, tmp_path / "job", execution=Execution(in_process=True))
    controller = load_controller(tmp_path / "job")
    assert hasattr(controller, "model")  # the BDD path of admits()
    rng = np.random.default_rng(1)
    cells = controller.sample_cells(6, rng)
    grids = controller.input_grids
    every = np.array([[a, b] for a in grids[0].axis_points(0) for b in grids[1].axis_points(0)])
    for x in controller.state_grid.points(cells):
        listed = {tuple(u) for u in controller.inputs(x).tolist()}
        assert listed
        assert {tuple(u) for u in every.tolist() if admits(controller, x, u)} == listed
    assert not admits(controller, np.array([-50.0, 0.0]), every[0])  # off the grid: nothing is admissible


def _cube(x0_in_domain: bool, x0: list[float]) -> FigureSetting:
    grid = UniformGrid.covering([0, 0, 0], [4, 4, 4], 1.0)
    return FigureSetting("cube", "reach", grid, ("x1", "x2", "x3"), ("u1",), {}, x0=np.array(x0),
                         x0_in_domain=x0_in_domain)


def _start_run(x: list[float]) -> tuple[str, np.ndarray, Run]:
    start = np.array([x])
    return "random", start[0], Run(start, np.zeros((0, 1)), np.zeros(1, dtype=bool))


@pytest.mark.parametrize("x0,on_slice", [([2.2, 0.4, 3.1], False), ([2.2, 0.4, 1.1], True)])
def test_an_initial_state_outside_the_domain_is_drawn_only_on_its_slice(x0, on_slice):
    """The slice passes through the first run's start (x3 = 1); x0 off it is said, not drawn."""
    setting = _cube(False, x0)
    ax = phase_plane(setting, lambda idx: np.ones(idx.shape[0], dtype=bool), [_start_run([1.0, 1.0, 1.0])]).axes[0]
    title = " ".join(ax.get_title(loc="left").split())
    drawn = any(line.get_gid() == "x0_outside" for line in ax.lines)
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert drawn == on_slice
    assert ("x0 = [2.2, 0.4, 3.1] (not in the domain) lies off this slice: not drawn" in title) == (not on_slice)
    assert not any("off this slice" in text for text in legend)
