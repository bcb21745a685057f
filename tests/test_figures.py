"""The figures a control engineer reads: what the phase plane and the time plot draw (domain cells with their
extents, the spec's boxes, the runs' states, the inputs as applied), read back from the matplotlib objects, and
the redrawing of a finished job's figures (``compabs figures DIR``)."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from matplotlib.image import AxesImage
from matplotlib.patches import Rectangle

from pipelines.controller_loading import load_controller
from pipelines.errors import SpecError
from pipelines.figures import figure_setting, phase_plane, time_plot
from pipelines.figures.phase_plane import cell_edges, check_axes
from pipelines.grid import UniformGrid
from pipelines.spec.model import parse_spec
from pipelines.spec.regions import closed_loop_regions
from pipelines.verification.closed_loop import Run, simulate, simulate_many
from service.figures_cmd import add_parser, axes_pair
from workers import jobdir
from workers.control import run_synthesis
from workers.figures import redraw_figures
from workers.job import run_abstraction

AGENT = {"state": {"lb": 0, "ub": 10, "eta": 0.5}, "input": {"lb": -1, "ub": 1, "eta": 0.5}, "reads": [0],
         "dynamics": "x[0] + u[0] + 0.05 * (w[0] - x[0])", "lipschitz": {"x": 0.95, "w": 0.05},
         "samples": 20, "growth_bound": "lipschitz"}
TARGET = ([7.5, 7.5], [10, 10])
OBSTACLES = [([3, 0], [4, 5]), ([6, 5], [7, 10])]


def rover_spec():
    """Two coupled single integrators on [0, 10]^2: reach the top-right corner around two walls."""
    return parse_spec({
        "name": "rover",
        "subsystems": [{"name": "east", **AGENT}, {"name": "north", **AGENT}],
        "interconnection": {"map": "mean(x)", "internal": {"lb": 0, "ub": 10, "eta": 0.5}, "samples": 20,
                            "alpha": 0.01, "error": "linear"},
        "specification": {"kind": "reach_avoid", "target": {"boxes": [{"lb": TARGET[0], "ub": TARGET[1]}]},
                          "avoid": {"boxes": [{"lb": lb, "ub": ub} for lb, ub in OBSTACLES]}},
        "options": {"audit_transitions": 1000, "initial_states": [[1, 1]], "closed_loop_runs": 10, "seed": 3},
    })


@pytest.fixture(scope="module")
def rover(tmp_path_factory):
    """A finished rover job: controller, figures, spec.json and report.json (what ``compabs run`` leaves)."""
    out = tmp_path_factory.mktemp("rover")
    spec = rover_spec()
    abstraction = run_abstraction(spec)
    report = run_synthesis(abstraction, out)
    jobdir.write_spec(out, spec)
    jobdir.write_report(out, report)
    return out, abstraction.network, report


def _runs(network, controller, X0, steps=60):
    regions = closed_loop_regions(network.spec, network)
    runs = simulate_many(network, controller, np.asarray(X0, dtype=float), steps, np.random.default_rng(0),
                         network.spec.specification.kind, regions["target"], regions["avoid"], choose="first",
                         safe=regions["safe"])
    return [("initial" if r == 0 else "random", np.asarray(X0[r], dtype=float), run) for r, run in enumerate(runs)]


def _by_gid(ax, kind):
    return {a.get_gid(): a for a in getattr(ax, kind) if a.get_gid()}


def test_phase_plane_draws_the_domain_the_boxes_and_the_runs(rover):
    out, network, report = rover
    controller = load_controller(out)
    grid = network.composed_state_grid()
    setting = figure_setting(network, [{"x0": [1.0, 1.0], "in_domain": True}])
    runs = _runs(network, controller, [[1.0, 1.0], [8.5, 1.0], [1.0, 9.0]])
    fig = phase_plane(setting, controller.in_domain, runs)
    ax = fig.axes[0]

    # The domain: one pixel per cell, cells point ± eta/2, the mask being the controller's, cell for cell.
    (image,) = [a for a in ax.get_images() if a.get_gid() == "domain"]
    assert isinstance(image, AxesImage)
    np.testing.assert_allclose(image.get_extent(), [-0.25, 10.25, -0.25, 10.25])
    cells = grid.unravel(np.arange(grid.size))
    expected = controller.in_domain(cells).reshape(grid.shape)
    np.testing.assert_array_equal(np.asarray(image.get_array()).T.astype(bool), expected)
    assert expected.sum() == report["domain_states"] > 0

    # The spec's boxes, with their own extents, and the obstacles hatched.
    patches = _by_gid(ax, "patches")
    for gid, (lb, ub) in [("target:0", TARGET), ("avoid:0", OBSTACLES[0]), ("avoid:1", OBSTACLES[1])]:
        rect = patches[gid]
        assert isinstance(rect, Rectangle)
        np.testing.assert_allclose([rect.get_x(), rect.get_y(), rect.get_x() + rect.get_width(),
                                    rect.get_y() + rect.get_height()], [*lb, *ub])
    assert patches["avoid:0"].get_hatch() and patches["avoid:1"].get_hatch()
    np.testing.assert_allclose(patches["state_set"].get_bbox().bounds, [0, 0, 10, 10])

    # Every run, its start and end marked, with the run's own states.
    lines = _by_gid(ax, "lines")
    for r, (_, x0, run) in enumerate(runs):
        np.testing.assert_array_equal(lines[f"run:{r}"].get_xdata(), run.states[:, 0])
        np.testing.assert_array_equal(lines[f"run:{r}"].get_ydata(), run.states[:, 1])
        np.testing.assert_array_equal(np.r_[lines[f"start:{r}"].get_xdata(), lines[f"start:{r}"].get_ydata()], x0)
        np.testing.assert_array_equal(np.r_[lines[f"end:{r}"].get_xdata(), lines[f"end:{r}"].get_ydata()],
                                      run.states[-1])
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    for label in ("target", "obstacle (avoid)", "state set X", "closed loop from x0",
                  "closed loop from random domain states", "start", "end"):
        assert label in legend
    assert f"winning domain ({report['domain_states']} of {grid.size} cells)" in legend
    assert legend.count("obstacle (avoid)") == 1  # one entry for every obstacle box
    title = ax.get_title(loc="left")
    assert "reach-avoid" in title and "x0 = [1, 1] is in the controller's domain" in title
    assert ax.get_xlabel() == "x1 (east)" and ax.get_ylabel() == "x2 (north)"
    assert ax.get_aspect() == 1.0


def test_time_plot_bands_steps_and_inputs_as_applied(rover):
    out, network, _ = rover
    controller = load_controller(out)
    setting = figure_setting(network, [{"x0": [1.0, 1.0], "in_domain": True}])
    ((_, x0, run),) = _runs(network, controller, [[1.0, 1.0]])
    assert run.violation is None and run.inputs.shape[0] > 3
    free = simulate(network, None, x0, run.inputs.shape[0], np.random.default_rng(0), "reach_avoid")
    fig = time_plot(setting, run, free=free)
    state_axes, input_ax = fig.axes[:2], fig.axes[2]
    for c, ax in enumerate(state_axes):
        lines = _by_gid(ax, "lines")
        np.testing.assert_array_equal(lines[f"state:{c}"].get_ydata(), run.states[:, c])
        np.testing.assert_array_equal(lines[f"free:{c}"].get_ydata(), free.states[:, c])
        band = _by_gid(ax, "patches")[f"target_band:{c}:0"]
        np.testing.assert_allclose([band.get_y(), band.get_y() + band.get_height()], [TARGET[0][c], TARGET[1][c]])
    inputs = _by_gid(input_ax, "lines")
    for j in range(2):
        line = inputs[f"input:{j}"]
        assert line.get_drawstyle() == "steps-post"
        np.testing.assert_array_equal(line.get_ydata()[:-1], run.inputs[:, j])  # no jitter: as applied
        assert line.get_ydata()[-1] == run.inputs[-1, j]
    for ax in fig.axes:  # legends outside the axes, on the right
        legend = ax.get_legend()
        assert legend is not None and legend.get_bbox_to_anchor().x0 > ax.get_window_extent().x1 - 1
    title = fig.axes[0].get_title(loc="left")
    assert "reach-avoid" in title and "x0 = [1, 1] is in" in title and f"k = {run.inputs.shape[0]}" in title


def test_inputs_zero_over_the_run_are_a_note_not_curves(rover):
    _, network, _ = rover
    setting = figure_setting(network, [{"x0": [1.0, 1.0], "in_domain": False}])
    states = np.array([[1.0, 1.0], [2.0, 1.0], [3.0, 1.0]])
    run = Run(states, np.array([[1.0, 0.0], [1.0, 0.0]]), np.zeros(3, dtype=bool), violation="cut short")
    fig = time_plot(setting, run, origin="random")
    input_ax = fig.axes[-1]
    assert set(_by_gid(input_ax, "lines")) == {"input:0"}
    assert any("u2 (north): 0 at every step" in t.get_text() for t in input_ax.texts)
    title = fig.axes[0].get_title(loc="left")
    assert "is NOT in the controller's domain" in title and "violation: cut short" in title


def test_a_slice_of_three_coordinates_is_through_the_cell_of_x0():
    grid = UniformGrid.covering([0, 0, 0], [4, 4, 4], 1.0)
    far = (np.array([0.0, 0.0, 3.6]), np.array([4.0, 4.0, 4.0]))  # misses the slice x3 = 1 (cell [0.5, 1.5])
    near = (np.array([1.0, 1.0, 0.0]), np.array([2.0, 3.0, 1.2]))
    from pipelines.figures.setting import FigureSetting

    setting = FigureSetting("cube", "reach_avoid", grid, ("x1 (a)", "x2 (b)", "x3 (c)"), ("u1 (a)",),
                            {"target": [near], "avoid": [far]}, x0=np.array([2.2, 0.4, 1.1]), x0_in_domain=True)
    seen = []

    def in_domain(idx):
        seen.append(idx.copy())
        return (idx[:, 0] + idx[:, 1]) % 2 == 0

    ax = phase_plane(setting, in_domain, [], axes=(1, 0)).axes[0]
    assert np.all(np.concatenate(seen)[:, 2] == 1)  # every cell asked about is in the slice x3 = 1
    (image,) = ax.get_images()
    np.testing.assert_array_equal(np.asarray(image.get_array()).T,
                                  (np.add.outer(np.arange(5), np.arange(5)) % 2 == 0).astype(np.int8))
    patches = _by_gid(ax, "patches")
    assert "target:0" in patches and "avoid:0" not in patches
    np.testing.assert_allclose(patches["target:0"].get_bbox().bounds, [1, 1, 2, 1])  # x2 on x, x1 on y
    assert "slice through the cell of x0" in ax.get_title(loc="left")
    assert "avoid: no box meets this slice" in ax.get_title(loc="left")


@settings(max_examples=50, deadline=None)
@given(lb=st.floats(-50, 50), width=st.floats(0.1, 30), eta=st.floats(0.05, 5), origin=st.floats(-3, 3))
def test_cell_edges_are_the_cells(lb, width, eta, origin):
    grid = UniformGrid.covering(lb, lb + width, eta, origin)
    edges = cell_edges(grid, 0)
    p = grid.axis_points(0)
    np.testing.assert_allclose(edges[:-1], p - eta / 2)
    np.testing.assert_allclose(edges[1:], p + eta / 2)
    assert edges[0] <= lb + 1e-9 * max(1, abs(lb)) and edges[-1] >= lb + width - 1e-9 * max(1, abs(lb + width))


def test_bad_axes_are_refused():
    assert check_axes([1, 0], 3) == (1, 0)
    for axes, n in [((0, 0), 2), ((0, 2), 2), ((0,), 2), ((-1, 0), 2), ((0, 1), 1)]:
        with pytest.raises(SpecError):
            check_axes(axes, n)


def test_the_job_draws_its_figures_deterministically(rover):
    out, _, report = rover
    assert report["figures"] == ["trajectory.png", "phase_plane.png"]
    example = json.loads((out / jobdir.EXAMPLE_RUN).read_text())
    assert example["choose"] == "steady" and example["starts"][0] == {"origin": "initial", "x0": [1.0, 1.0]}
    assert len(example["starts"]) == 1 + 5 and example["controlled"]["violation"] is None
    for name in report["figures"]:
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_redraw_figures_from_the_job_directory(rover, tmp_path):
    out, _, report = rover
    before = json.loads((out / jobdir.EXAMPLE_RUN).read_text())
    for name in report["figures"]:
        (out / name).unlink()
    paths = redraw_figures(out, axes=(1, 0))
    assert [p.name for p in paths] == report["figures"] and all(p.is_file() for p in paths)
    assert json.loads((out / jobdir.EXAMPLE_RUN).read_text()) == before  # the same runs, run again

    # A job drawn before the starts were kept: they come from its seed, as its closed loop drew them.
    old = json.loads((out / jobdir.EXAMPLE_RUN).read_text())
    try:
        (out / jobdir.EXAMPLE_RUN).write_text(json.dumps({"controlled": old["controlled"], "free": old["free"]}))
        assert [p.name for p in redraw_figures(out)] == report["figures"]
        again = json.loads((out / jobdir.EXAMPLE_RUN).read_text())
        assert again["starts"][0] == {"origin": "initial", "x0": [1.0, 1.0]} and len(again["starts"]) == 6
    finally:
        (out / jobdir.EXAMPLE_RUN).write_text(json.dumps(old))

    with pytest.raises(SpecError, match="different state coordinates"):
        redraw_figures(out, axes=(0, 2))
    with pytest.raises(jobdir.ArtifactError, match="not a finished job"):
        redraw_figures(tmp_path)


def test_the_figures_command(rover, capsys):
    out, _, report = rover
    parser = argparse.ArgumentParser(prog="compabs")
    add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["figures", str(out), "--axes", "1, 0"])
    assert args.axes == (1, 0) and args.func(args) == 0
    assert [line.rsplit("/", 1)[-1] for line in capsys.readouterr().out.split()] == report["figures"]
    for bad in ("0", "a,b", "0,1,2", "-1,0"):
        with pytest.raises(argparse.ArgumentTypeError):
            axes_pair(bad)
