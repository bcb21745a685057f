"""The figures of every example (issue 25): each example is run (abstraction, synthesis, closed loop, figures; the
costly ones on a reduced copy of their YAML that keeps the specification: kind, target, safe set, obstacles), and
its figures are read back from the matplotlib objects ``compabs run`` saved:

* the phase plane draws the winning domain cell for cell as the controller has it (or, on a plane of more than
  ``MAX_IMAGE_SIDE`` cells a side, in blocks: never a block as domain where a cell of it is not), through a
  slice that meets the domain; the spec's target, safe set and obstacles with their own extents (those that
  meet the slice); the closed-loop runs drawn, each starting at its start; a title giving the spec kind, x0 and
  whether it is in the domain;
* the time plot draws the run's states from x0, the target (and safe) band of each coordinate, for a consensus
  target the box holding the state at each step, the inputs as applied (steps), and the same title.

What a user sees in each figure is described in the notes of issue 25.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from matplotlib.figure import Figure
from matplotlib.image import AxesImage
from matplotlib.patches import Rectangle

import workers.figures as worker_figures
from pipelines.array_controller import ArrayController
from pipelines.controller import Controller
from pipelines.controller_loading import load_controller
from pipelines.figures import FigureSetting, phase_plane, time_plot
from pipelines.figures.domain import block_factors, block_levels, plane_mask
from pipelines.figures.phase_plane import MAX_IMAGE_SIDE, MAX_SLICE_CELLS, cell_edges
from pipelines.figures.setting import vector
from pipelines.grid import UniformGrid
from pipelines.network import Network
from pipelines.spec.model import JobSpec, load_spec
from pipelines.verification.closed_loop import Run
from workers import jobdir
from workers.control import run_synthesis
from workers.job import run_abstraction

from .conftest import EXAMPLES

KIND_WORDS = {"safe": "safe", "reach": "reach", "reach_avoid": "reach-avoid", "reach_and_stay": "reach-and-stay"}
REGION_LABELS = {"target": "target", "safe": "safe set", "avoid": "obstacle (avoid)"}


# ============================================================================================== reduced examples
def _consensus(d: dict) -> None:
    """N = 8 -> 4 agents (the slice is still a plane through 2 of them); x0: the paper's first 4 agents."""
    d["parameters"]["N"] = 4
    d["options"]["initial_states"] = [d["options"]["initial_states"][0][:4]]


def _stress(d: dict) -> None:
    """Synthesis on (the runner benchmark turns it off), on a grid 8x coarser with 100 samples per cell."""
    d["options"]["synthesis"] = True
    d["subsystems"][0]["samples"] = 100
    d["subsystems"][0]["state"]["eta"] = d["interconnection"]["internal"]["eta"] = 0.5


def _dcdc(d: dict) -> None:
    """SCOTS's grid (641,601 cells: above the per-cell cap, drawn in blocks), fewer samples and runs."""
    d["subsystems"][0]["samples"] = 4
    d["options"]["closed_loop_runs"] = 10


def _vehicle(d: dict) -> None:
    """Every second input (16 of 49: spacing 0.6 on points offset by 0.3), fewer runs."""
    d["subsystems"][0]["input"]["eta"] = 0.6
    d["subsystems"][0]["input"]["origin"] = 0.3
    d["options"]["closed_loop_runs"] = 10


def _rooms(d: dict) -> None:
    """Fewer closed-loop runs (the synthesis is the cost, and it is the example's)."""
    d["options"]["closed_loop_runs"] = 10


REDUCE = {"small": None, "scalability": None, "consensus": _consensus, "stress": _stress, "rooms": _rooms,
          "tanks": None, "dcdc": _dcdc, "vehicle": _vehicle}
SLOW = {"rooms", "tanks", "dcdc", "vehicle"}


@dataclass
class Job:
    name: str
    spec: JobSpec
    network: Network
    controller: Controller | ArrayController
    report: dict
    out: Path
    figures: dict[str, Figure]
    drawn: list[tuple[str, np.ndarray, Run]]  # the runs on the phase plane, as phase_plane got them
    setting: FigureSetting
    example: dict = field(default_factory=dict)  # closed_loop_example.json

    @property
    def grid(self) -> UniformGrid:
        return self.network.composed_state_grid()

    @property
    def x0(self) -> tuple[np.ndarray | None, bool | None]:
        initial = self.report["closed_loop"]["initial_states"]
        return (np.asarray(initial[0]["x0"], dtype=float), bool(initial[0]["in_domain"])) if initial else (None, None)


def run_example(name: str, tmp: Path) -> Job:
    """The example (reduced by a copy of its YAML in ``tmp``) as ``compabs run`` runs it in this process, with the
    Figure objects it saves."""
    path = EXAMPLES / f"{name}.yaml"
    reduce = REDUCE[name]
    if reduce is not None:
        data = yaml.safe_load(path.read_text())
        reduce(data)
        path = tmp / f"{name}.yaml"
        path.write_text(yaml.safe_dump(data))
    spec = load_spec(path)
    original = load_spec(EXAMPLES / f"{name}.yaml")
    assert spec.specification == original.specification  # the reductions keep what the figures draw
    abstraction = run_abstraction(spec, audit=False)
    out = tmp / "job"
    figures: dict[str, Figure] = {}
    drawn: dict[str, Any] = {}
    save, draw = worker_figures.save_figure, worker_figures.phase_plane

    def saving(fig, where):
        figures[Path(where).stem] = fig
        return save(fig, where)

    def drawing(setting, in_domain, runs, **kw):
        drawn["runs"], drawn["setting"] = list(runs), setting
        return draw(setting, in_domain, runs, **kw)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(worker_figures, "save_figure", saving)
        mp.setattr(worker_figures, "phase_plane", drawing)
        report = run_synthesis(abstraction, out)
    jobdir.write_spec(out, spec)
    jobdir.write_report(out, {**abstraction.report, **report})
    controller = load_controller(out)
    assert isinstance(controller, Controller | ArrayController)  # single systems: an explicit game's arrays
    example = json.loads((out / jobdir.EXAMPLE_RUN).read_text())
    return Job(name, spec, abstraction.network, controller, report, out, figures, drawn["runs"], drawn["setting"],
               example)


@pytest.fixture(scope="module", params=[pytest.param(n, marks=[pytest.mark.slow] if n in SLOW else [])
                                        for n in REDUCE])
def job(request, tmp_path_factory) -> Job:
    return run_example(request.param, tmp_path_factory.mktemp(request.param))


# ============================================================================================== reading figures
def by_gid(ax, kind: str) -> dict[str, Any]:
    return {a.get_gid(): a for a in getattr(ax, kind) if a.get_gid()}


def spec_boxes(job: Job, key: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """The region's boxes over the composed state, from the spec itself (scalars broadcast, consensus boxes)."""
    region = getattr(job.spec.specification, key)
    n = job.network.state_dim
    boxes = [(np.broadcast_to(np.asarray(b.lb, dtype=float), (n,)),
              np.broadcast_to(np.asarray(b.ub, dtype=float), (n,))) for b in region.boxes]
    if region.consensus is not None:
        first, last, step = region.consensus.centers
        r = region.consensus.radius
        boxes += [(np.full(n, phi - r), np.full(n, phi + r))
                  for phi in first + step * np.arange(int(math.floor((last - first) / step + 1e-9)) + 1)]
    return boxes


def title_states_the_setting(title: str, job: Job) -> None:
    assert f"{KIND_WORDS[job.spec.specification.kind]} specification" in title
    x0, inside = job.x0
    if x0 is None:
        assert "no initial state in the spec" in title
    else:
        assert f"initial state x0 = {vector(x0)} is {'in' if inside else 'NOT in'} the controller's domain" in title


def expected_slice(job: Job) -> np.ndarray:
    """The cell the phase plane's slice passes through: that of x0 if it is in the domain, else where the first
    drawn run starts (a domain state)."""
    x0, inside = job.x0
    at = x0 if inside else job.drawn[0][1]
    idx, ok = job.grid.cell_of(np.asarray(at)[None, :])
    assert ok[0]
    return idx[0]


# ============================================================================================== the phase plane
def test_phase_plane_draws_domain_regions_and_runs(job: Job):
    grid, n = job.grid, job.network.state_dim
    fig = job.figures["phase_plane"]
    ax = fig.axes[0]
    title = " ".join(ax.get_title(loc="left").split())  # unwrapped
    title_states_the_setting(title, job)
    base = expected_slice(job)
    ei, ej = cell_edges(grid, 0), cell_edges(grid, 1)
    window = [ei[0], ei[-1], ej[0], ej[-1]]
    np.testing.assert_allclose([*ax.get_xlim(), *ax.get_ylim()], window)
    if n > 2:
        through = "the cell of x0" if job.x0[1] else "the cell where the first drawn run starts"
        assert f"slice through {through}" in title
    assert "x0 is off the grid" not in title  # no example has one off its grid

    # The domain: the controller's, cell for cell (the BDD read in one pass = one query per cell).
    (image,) = [a for a in ax.get_images() if a.get_gid() == "domain"]
    assert isinstance(image, AxesImage)
    mask = plane_mask(job.controller, base, 0, 1)
    assert mask.shape == (grid.shape[0], grid.shape[1])
    cells = np.repeat(base[None, :], mask.size, axis=0)
    cells[:, :2] = np.stack(np.meshgrid(np.arange(mask.shape[0]), np.arange(mask.shape[1]), indexing="ij"),
                            axis=-1).reshape(-1, 2)
    rng = np.random.default_rng(0)
    asked = np.arange(mask.size) if mask.size <= 20_000 else rng.choice(mask.size, 20_000, replace=False)
    truth = job.controller.in_domain(cells[asked])
    np.testing.assert_array_equal(mask.ravel()[asked], truth)
    if n == 2:
        assert mask.sum() == job.report["domain_states"]
    assert mask[base[0], base[1]]  # the slice meets the domain
    data = np.asarray(image.get_array()).T
    factors = block_factors(mask.shape, MAX_IMAGE_SIDE)
    if factors == (1, 1):  # one pixel per cell, cells point ± eta/2
        np.testing.assert_array_equal(data.astype(bool), mask)
        np.testing.assert_allclose(image.get_extent(), window)
    else:  # blocks: a block is drawn as domain only where every cell of it is
        assert job.name == "dcdc" and max(data.shape) <= MAX_IMAGE_SIDE
        np.testing.assert_array_equal(data, block_levels(mask, factors))
        bi, bj = cells[asked, 0] // factors[0], cells[asked, 1] // factors[1]
        assert not np.any((data[bi, bj] == 2) & ~truth) and not np.any((data[bi, bj] == 0) & truth)
        lo_x, hi_x, lo_y, hi_y = image.get_extent()
        np.testing.assert_allclose([lo_x, lo_y], [window[0], window[2]])
        np.testing.assert_allclose([hi_x, hi_y], [window[0] + data.shape[0] * factors[0] * grid.eta[0],
                                                  window[2] + data.shape[1] * factors[1] * grid.eta[1]])
        assert "drawn in blocks of" in title
    legend_box = ax.get_legend()
    assert legend_box is not None
    legend = [t.get_text() for t in legend_box.get_texts()]
    assert any(t.startswith(f"winning domain ({int(mask.sum()):,} of {mask.size:,} cells)") for t in legend)

    # The spec's regions with their own extents: every box that meets the slice, and only those.
    patches = by_gid(ax, "patches")
    centre = grid.points(base[None, :])[0]
    others = np.arange(2, n)
    main = "safe" if job.spec.specification.kind == "safe" else "target"
    for key in ("target", "safe", "avoid"):
        if getattr(job.spec.specification, key) is None:
            assert not any(g.startswith(f"{key}:") for g in patches)
            continue
        drawn = 0
        for k, (lb, ub) in enumerate(spec_boxes(job, key)):
            half = grid.eta_array[others] / 2
            meets = np.all((lb[others] <= centre[others] + half) & (ub[others] >= centre[others] - half))
            lo = np.maximum([lb[0], lb[1]], [window[0], window[2]])
            hi = np.minimum([ub[0], ub[1]], [window[1], window[3]])
            if not meets or np.any(lo > hi):
                assert f"{key}:{k}" not in patches
                continue
            rect = patches[f"{key}:{k}"]
            assert isinstance(rect, Rectangle)
            np.testing.assert_allclose([rect.get_x(), rect.get_y(), rect.get_x() + rect.get_width(),
                                        rect.get_y() + rect.get_height()], [*lo, *hi])
            assert bool(rect.get_hatch()) == (key == "avoid")
            drawn += 1
        assert drawn > 0 or key != main, f"{key}: no box drawn"
        assert (REGION_LABELS[key] in legend) == (drawn > 0)
    if job.name == "vehicle":
        assert sum(g.startswith("avoid:") for g in patches) == 15

    # The closed-loop runs: every run drawn, from its start; the spec's x0 first when it is in the domain.
    lines = by_gid(ax, "lines")
    assert len(job.drawn) >= 1
    for r, (_, start, run) in enumerate(job.drawn):
        line = lines[f"run:{r}"]
        np.testing.assert_array_equal(line.get_xdata(), run.states[:, 0])
        np.testing.assert_array_equal(line.get_ydata(), run.states[:, 1])
        np.testing.assert_array_equal(run.states[0], start)
        np.testing.assert_array_equal(np.r_[lines[f"start:{r}"].get_xdata(), lines[f"start:{r}"].get_ydata()],
                                      start[:2])
    x0, inside = job.x0
    if inside:
        assert job.drawn[0][0] == "initial"
        np.testing.assert_array_equal(job.drawn[0][1], x0)
        assert "closed loop from x0" in legend
    else:
        assert all(origin == "random" for origin, _, _ in job.drawn)
    if x0 is not None and not inside:  # marked where it lies on the slice, else said to lie off it: never both
        x0_cell, on_grid = grid.cell_of(np.asarray(x0, dtype=float)[None, :])
        off = n > 2 and not (on_grid[0] and np.array_equal(x0_cell[0][2:], np.asarray(base)[2:]))
        assert ("(not in the domain) lies off this slice: not drawn" in title) == off, title
        assert ("x0_outside" in lines) == (not off)
        assert not any("off this slice" in text for text in legend)
        if not off:
            np.testing.assert_array_equal(np.r_[lines["x0_outside"].get_xdata(), lines["x0_outside"].get_ydata()],
                                          x0[:2])
    if x0 is None:
        assert "from x0" not in title


# ============================================================================================== the time plot
def test_time_plot_draws_states_bands_and_inputs(job: Job):
    n, kind = job.network.state_dim, job.spec.specification.kind
    fig = job.figures["trajectory"]
    controlled = job.example["controlled"]
    states, inputs = np.asarray(controlled["states"]), np.asarray(controlled["inputs"]).reshape(-1, len(
        job.setting.input_names))
    in_target = np.asarray(controlled["in_target"], dtype=bool)
    np.testing.assert_array_equal(states[0], job.example["x0"])
    x0, inside = job.x0
    if inside:
        assert x0 is not None and job.example["origin"] == "initial" and np.array_equal(job.example["x0"], x0)
    else:  # the longest run drawn (a random start may already be in the target: no step to show)
        assert job.example["origin"] == "random"
        assert states.shape[0] == max(run.states.shape[0] for _, _, run in job.drawn) > 1
    panels = n if n <= 4 else 1
    state_axes, input_ax = fig.axes[:panels], fig.axes[panels]
    assert len(fig.axes) == panels + 1
    title = " ".join(state_axes[0].get_title(loc="left").split())
    title_states_the_setting(title, job)

    # States: each coordinate's run from x0.
    for c in range(n):
        line = by_gid(state_axes[c if panels > 1 else 0], "lines")[f"state:{c}"]
        np.testing.assert_array_equal(line.get_ydata(), states[:, c])
        np.testing.assert_array_equal(line.get_xdata(), np.arange(states.shape[0]))

    # The target (or safe) band of every coordinate: boxes as spans, a consensus region as the box holding the state.
    keys = ["safe"] if kind == "safe" else ["target"] + (["safe"] if job.spec.specification.safe else [])
    for key in keys:
        region = getattr(job.spec.specification, key)
        for c in range(n):
            ax = state_axes[c if panels > 1 else 0]
            where = c if panels > 1 else "all"
            patches = by_gid(ax, "patches")
            intervals = sorted({(float(lb[c]), float(ub[c])) for lb, ub in spec_boxes(job, key)[: len(region.boxes)]})
            for k, (lo, hi) in enumerate(intervals):
                band = patches[f"{key}_band:{where}:{k}"]
                np.testing.assert_allclose([band.get_y(), band.get_y() + band.get_height()], [lo, hi])
            if region.consensus is None:
                assert intervals
                continue
            r = region.consensus.radius
            stretches = [p for g, p in patches.items() if g.startswith(f"{key}_band:{where}:consensus:")]
            assert stretches, "a consensus region has its band"
            for p in stretches:
                assert p.get_height() == pytest.approx(2 * r)
                phi = p.get_y() + r
                first, last, step = region.consensus.centers
                centre = (phi - first) / step
                assert first - 1e-9 <= phi <= last + 1e-9 and abs(centre - round(centre)) < 1e-9
            for t in np.flatnonzero(in_target if key == "target" else np.ones(len(states), bool)):
                held = [p for p in stretches if p.get_x() < t < p.get_x() + p.get_width()]
                assert len(held) == 1, f"step {t}: the state is in the target, a band must hold it"
                assert np.all((states[t] >= held[0].get_y() - 1e-9)
                              & (states[t] <= held[0].get_y() + held[0].get_height() + 1e-9))
        assert "no band drawn" not in title

    # Inputs as applied, as steps; those 0 throughout named above their panel, not drawn over the others.
    K = inputs.shape[0]
    assert K == states.shape[0] - 1
    lines = by_gid(input_ax, "lines")
    zero = [j for j in range(inputs.shape[1]) if not np.any(inputs[:, j])]
    for j in range(inputs.shape[1]):
        if j in zero and K:
            assert f"input:{j}" not in lines
            continue
        line = lines[f"input:{j}"]
        assert line.get_drawstyle() == "steps-post"
        np.testing.assert_array_equal(line.get_ydata()[:-1], inputs[:, j])
        assert line.get_ydata()[-1] == inputs[-1, j]
    if zero and K:
        (note,) = input_ax.texts
        assert "0 at every step" in note.get_text()
        assert note.get_position()[1] >= 1 and note.get_verticalalignment() == "bottom"  # above the panel
    ticks = [t for t in input_ax.get_xticks() if input_ax.get_xlim()[0] <= t <= input_ax.get_xlim()[1]]
    assert ticks and all(float(t).is_integer() for t in ticks)  # time steps


# ============================================================================================== the limits
def test_a_plane_above_the_per_cell_cap_says_so_in_the_title(tmp_path_factory):
    """Without the domain BDD (cells asked one by one), a plane of more than MAX_SLICE_CELLS cells is not drawn, and
    the title says so; the job (with the BDD) draws it in blocks (test above, dcdc)."""
    grid = UniformGrid.covering([0, 0], [1, 1], 1.0 / 600)
    assert grid.size > MAX_SLICE_CELLS
    setting = FigureSetting("big", "safe", grid, ("x1 (a)", "x2 (b)"), ("u1 (a)",),
                            {"safe": [(np.zeros(2), np.ones(2))]}, x0=np.array([0.5, 0.5]), x0_in_domain=True)

    def in_domain(idx):
        raise AssertionError("not asked above the cap")

    ax = phase_plane(setting, in_domain, []).axes[0]
    assert not ax.get_images()
    title = " ".join(ax.get_title(loc="left").split())
    assert f"domain not drawn: {grid.size:,} cells on this plane (at most {MAX_SLICE_CELLS:,})" in title
    patches = by_gid(ax, "patches")
    np.testing.assert_allclose(patches["safe:0"].get_bbox().bounds, [0, 0, 1, 1])

    # With a plane of the domain, drawn in blocks: wholly in (2), partly (1), not at all (0).
    mask = np.zeros(grid.shape, dtype=bool)
    mask[:300, :] = True
    mask[300, :5] = True
    ax = phase_plane(setting, in_domain, [], plane=lambda base, i, j: mask).axes[0]
    (image,) = ax.get_images()
    data = np.asarray(image.get_array()).T
    f = block_factors(grid.shape, MAX_IMAGE_SIDE)
    assert f == (2, 2) and data.shape == (math.ceil(grid.shape[0] / 2), math.ceil(grid.shape[1] / 2))
    assert np.all(data[:150] == 2) and data[150, 0] == 1 and data[150, 3] == 0 and np.all(data[151:] == 0)


def test_block_levels_never_draw_a_cell_outside_the_domain():
    mask = np.array([[1, 1, 1, 0, 1],
                     [1, 1, 1, 1, 1],
                     [0, 0, 0, 0, 1]], dtype=bool)
    np.testing.assert_array_equal(block_levels(mask, (2, 2)), [[2, 1, 2], [0, 0, 2]])
    rng = np.random.default_rng(1)
    for _ in range(50):
        m = rng.random(tuple(rng.integers(1, 30, 2))) < rng.random()
        f = (int(rng.integers(1, 5)), int(rng.integers(1, 5)))
        levels = block_levels(m, f)
        cells = levels[np.arange(m.shape[0])[:, None] // f[0], np.arange(m.shape[1])[None, :] // f[1]]
        assert not np.any((cells == 2) & ~m) and not np.any((cells == 0) & m)
        assert np.all(levels >= 0) and np.all(levels <= 2)


def test_short_runs_have_integer_time_steps():
    """A run of 2 steps: the time axis has the steps 0, 1, 2, not 0.25 ... (which read as half steps)."""
    grid = UniformGrid.covering([0, 0], [10, 10], 0.5)
    setting = FigureSetting("two", "reach", grid, ("x1 (a)", "x2 (b)"), ("u1 (a)", "u2 (b)"),
                            {"target": [(np.array([8.0, 8.0]), np.array([10.0, 10.0]))]},
                            bands={"target": [(np.array([8.0, 8.0]), np.array([10.0, 10.0]))]},
                            x0=np.array([7.0, 7.0]), x0_in_domain=True)
    run = Run(np.array([[7.0, 7.0], [7.5, 7.5], [8.5, 8.5]]), np.array([[1.0, 0.0], [1.0, 0.0]]),
              np.array([False, False, True]))
    fig = time_plot(setting, run)
    ax = fig.axes[-1]
    ticks = [t for t in ax.get_xticks() if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]
    assert ticks == [0, 1, 2]
