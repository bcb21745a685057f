"""The figures of a job (:mod:`pipelines.figures`), drawn into its directory after the closed loop, and redrawn
from a finished job directory (``compabs figures DIR``) without recomputing the abstraction.

The drawn runs start where the job's closed loop started (every initial state of the spec in the domain, and
the first :data:`FIGURE_RUNS` random domain states) and keep their input while it stays admissible, else take
the first admissible one (``steady``), so a figure is the same every time it is drawn and its inputs do not
chatter between extremes where several are admissible (inside a target); any admissible input meets the
specification (Theorem 4.2), so the figure shows a run the guarantee covers. The time plot draws the run from the spec's first initial state
when it is in the domain, else the longest of the random runs drawn. The starts are kept in
``closed_loop_example.json`` with the run drawn, and a redraw runs the concrete system again from them.

An ``ltl`` job's controller has memory: its runs track the automaton state and stop at acceptance
(:func:`~pipelines.verification.product_loop.simulate_product`, the first admissible input of the state's
controller), the trajectory figure colours the run by automaton state and names the formula's regions
(:func:`~pipelines.figures.automaton_plot.product_trajectory`), and the phase plane draws those regions.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from pipelines.array_controller import ArrayController
from pipelines.controller import Controller
from pipelines.controller_loading import load_controller
from pipelines.errors import CompabsError
from pipelines.figures import figure_setting, phase_plane, save_figure, time_plot
from pipelines.figures.automaton_plot import product_trajectory
from pipelines.figures.domain import plane_mask
from pipelines.figures.phase_plane import check_axes
from pipelines.network import Network, build_network
from pipelines.product_controller import ProductController
from pipelines.spec.model import JobSpec, parse_spec
from pipelines.spec.regions import closed_loop_regions
from pipelines.verification.closed_loop import ClosedLoop, simulate, simulate_many
from pipelines.verification.product_loop import simulate_product
from workers import jobdir
from workers.jobdir import ArtifactError

#: Random-start runs drawn on the phase plane, besides those from the spec's initial states.
FIGURE_RUNS = 5
#: How the drawn runs choose among the admissible inputs (:data:`pipelines.verification.closed_loop.CHOOSE`):
#: deterministic, and without chattering.
CHOICE = "steady"
#: The figures, by name (``DIR/<name>.png``), in the report's order.
FIGURES = ("trajectory", "phase_plane")

Start = tuple[str, np.ndarray]


def _figure_starts(starts: Sequence[Start]) -> list[Start]:
    """Every start from an initial state, then the first :data:`FIGURE_RUNS` random ones."""
    initial = [s for s in starts if s[0] == "initial"]
    return initial + [s for s in starts if s[0] != "initial"][:FIGURE_RUNS]


def _draw(network: Network, controller: Controller | ArrayController, starts: Sequence[Start], steps: int,
          initial_states: Sequence[dict], out_dir: Path, axes: Sequence[int]) -> list[Path]:
    """Run the concrete system from ``starts`` and draw every figure into ``out_dir``; returns their paths."""
    spec = network.spec
    kind = spec.specification.kind
    checked = closed_loop_regions(spec, network)
    target, avoid, safe = checked["target"], checked["avoid"], checked["safe"]
    chosen = _figure_starts(starts)
    X0 = np.array([x0 for _, x0 in chosen]).reshape(len(chosen), network.state_dim)
    # CHOICE draws nothing from the generator; it is only there for simulate's signature.
    rng = np.random.default_rng(0)
    runs = simulate_many(network, controller, X0, steps, rng, kind, target, avoid, choose=CHOICE, safe=safe)
    drawn = [(origin, x0, run) for (origin, x0), run in zip(chosen, runs)]
    setting = figure_setting(network, initial_states, CHOICE)
    paths = []
    if drawn:
        origin, x0, run = _shown(drawn)
        horizon = run.inputs.shape[0] or steps
        free = simulate(network, None, x0, horizon, rng, kind, target, avoid, safe=safe)
        fig = time_plot(setting, run, origin=origin, free=free, steps=horizon)
        paths.append(save_figure(fig, jobdir.figure(out_dir, "trajectory")))
        jobdir.write_example_run(out_dir, {
            "controlled": run.as_dict(), "free": free.as_dict(), "origin": origin, "x0": x0.tolist(),
            "choose": CHOICE, "steps": steps, "starts": [{"origin": o, "x0": x.tolist()} for o, x in chosen],
        })
    if network.state_dim >= 2:
        fig = phase_plane(setting, controller.in_domain, drawn, axes=axes, plane=partial(plane_mask, controller))
        paths.append(save_figure(fig, jobdir.figure(out_dir, "phase_plane")))
    return paths


def _shown(drawn: list[tuple[str, np.ndarray, Any]]) -> tuple[str, np.ndarray, Any]:
    """The run the time plot shows: the one from the spec's x0, else the longest of those drawn (the first may take
    no step)."""
    first = 0 if drawn[0][0] == "initial" else max(range(len(drawn)), key=lambda r: drawn[r][2].inputs.shape[0])
    return drawn[first]


#: How a controller with memory's drawn runs choose (deterministic; the previous input is no guide once the
#: automaton state, and with it the controller, changes).
PRODUCT_CHOICE = "first"


def _draw_product(network: Network, controller: ProductController, starts: Sequence[Start], steps: int,
                  initial_states: Sequence[dict], out_dir: Path, axes: Sequence[int]) -> list[Path]:
    """:func:`_draw` for a controller with memory (module docstring)."""
    chosen = _figure_starts(starts)
    X0 = np.array([x0 for _, x0 in chosen]).reshape(len(chosen), network.state_dim)
    runs = simulate_product(network, controller, X0, steps, np.random.default_rng(0), PRODUCT_CHOICE)
    drawn = [(origin, x0, run) for (origin, x0), run in zip(chosen, runs)]
    setting = figure_setting(network, initial_states, PRODUCT_CHOICE)
    paths = []
    if drawn:
        origin, x0, run = _shown(drawn)
        fig = product_trajectory(setting, run, run.extra["automaton_states"], controller.automaton, setting.atoms,
                                 axes=axes, origin=origin)
        paths.append(save_figure(fig, jobdir.figure(out_dir, "trajectory")))
        jobdir.write_example_run(out_dir, {
            "controlled": {**run.as_dict(), **run.extra}, "origin": origin, "x0": x0.tolist(),
            "choose": PRODUCT_CHOICE, "steps": steps, "starts": [{"origin": o, "x0": x.tolist()} for o, x in chosen],
        })
    if network.state_dim >= 2:
        fig = phase_plane(setting, controller.in_domain, drawn, axes=axes)
        paths.append(save_figure(fig, jobdir.figure(out_dir, "phase_plane")))
    return paths


def draw_figures(network: Network, controller: Controller | ArrayController | ProductController, loop: ClosedLoop,
                 out_dir: str | os.PathLike[str], *,
                 axes: Sequence[int] = (0, 1)) -> list[str]:
    """Draw the job's figures after its closed loop (:func:`workers.control.run_synthesis`).

    Parameters
    ----------
    network : Network
        The job's network (its ``spec`` names the kind and the regions).
    controller : Controller
    loop : ClosedLoop
        The job's closed loop: where its runs started, its horizon, which initial states are in the domain.
    out_dir : path
        The job directory: ``trajectory.png``, ``phase_plane.png`` (two or more state coordinates) and
        ``closed_loop_example.json`` are written there.
    axes : (int, int)
        The phase plane's coordinates, 0-based.

    Returns
    -------
    list of str
        The figures' file names, for the report.
    """
    if network.state_dim >= 2:
        check_axes(axes, network.state_dim)
    starts = [(origin, x0) for origin, x0, _ in loop.runs]
    if isinstance(controller, ProductController):
        paths = _draw_product(network, controller, starts, max(1, loop.steps), loop.initial_states, Path(out_dir),
                              axes)
    else:
        paths = _draw(network, controller, starts, loop.steps, loop.initial_states, Path(out_dir), axes)
    return [p.name for p in paths]


# ====================================================================================== redrawing a finished job
def _read_json(path: Path, what: str) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ArtifactError(f"{path}: the {what} cannot be read ({exc}); run the job again") from None


def _read_spec(out: Path) -> JobSpec:
    """``spec.json`` of a finished job (``report.json`` present)."""
    for name in (jobdir.SPEC, jobdir.REPORT):
        if not (out / name).is_file():
            raise ArtifactError(f"{out / name} is missing: {out} is not a finished job (report.json is written last); "
                                "give the --out directory of a finished 'compabs run'")
    return parse_spec(_read_json(out / jobdir.SPEC, "job spec"))


def _stored_starts(out: Path, n: int) -> tuple[list[Start], int] | None:
    """The starts and horizon ``closed_loop_example.json`` keeps (``None`` for a job drawn before it kept them)."""
    path = out / jobdir.EXAMPLE_RUN
    if not path.is_file():
        return None
    example = _read_json(path, "example run")
    if not isinstance(example, dict) or "starts" not in example:
        return None
    try:
        starts = [(str(s["origin"]), np.asarray(s["x0"], dtype=float)) for s in example["starts"]]
        steps = int(example["steps"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ArtifactError(f"{path}: damaged ({type(exc).__name__}: {exc}); run the job again") from None
    if any(x0.shape != (n,) for _, x0 in starts) or steps < 1:
        raise ArtifactError(f"{path}: its starts are not states of this job's {n} coordinates; run the job again")
    return starts, steps


def _initial_states(controller: Controller | ArrayController | ProductController, spec: JobSpec) -> list[dict]:
    """``x0`` and ``in_domain`` per initial state of the spec (as :attr:`ClosedLoop.initial_states`)."""
    out = []
    for x in spec.options.initial_states:
        x0 = np.asarray(x, dtype=float)
        idx = controller.cell(x0)
        out.append({"x0": x0.tolist(), "in_domain": idx is not None and bool(controller.in_domain(idx[None, :])[0])})
    return out


def _seeded_starts(controller: Controller | ArrayController | ProductController, spec: JobSpec, initial: list[dict], report: dict) -> tuple[list[Start], int]:
    """The starts the job's closed loop drew (:func:`run_closed_loop` with the generator of
    :func:`workers.control.run_synthesis`, ``seed + 1``), for a job whose example run does not keep them."""
    starts: list[Start] = [("initial", np.asarray(r["x0"], dtype=float)) for r in initial if r["in_domain"]]
    rng = np.random.default_rng(spec.options.seed + 1)
    cells = controller.sample_cells(spec.options.closed_loop_runs, rng) if spec.options.closed_loop_runs else None
    if cells is not None and cells.shape[0]:
        lo, hi = controller.state_grid.clipped_cells(cells)
        starts += [("random", x) for x in rng.uniform(lo, hi)]
    closed = report.get("closed_loop") if isinstance(report, dict) else None
    steps = closed.get("steps") if isinstance(closed, dict) else None
    return starts, int(steps or spec.options.closed_loop_steps or 100)


def redraw_figures(job_dir: str | os.PathLike[str], *, axes: tuple[int, int] = (0, 1),
                   allowed_modules: Sequence[str] | None = None) -> list[Path]:
    """Redraw every figure of a finished job from its directory: the spec, the network and the controller are
    read (nothing is abstracted or synthesized again) and the concrete system is run again from the stored
    starts (or, for an older job, from the starts its seed gives).

    Parameters
    ----------
    job_dir : path
        The ``--out`` directory of a finished ``compabs run`` (or a service job's directory).
    axes : (int, int)
        The phase plane's coordinates, 0-based.
    allowed_modules : sequence of str, optional
        Modules a ``module:function`` black box may come from (``None``: any, as on the local command line).

    Returns
    -------
    list of Path
        The figures written.

    Raises
    ------
    ArtifactError
        The directory is not a finished job, or a file of it is damaged.
    SpecError
        ``axes`` are not two different state coordinates.
    CompabsError
        The job has no controller (it ran with ``--no-synthesis``).
    """
    out = Path(job_dir)
    if not out.is_dir():
        raise ArtifactError(f"{out} is not a directory; give the --out directory of a finished 'compabs run'")
    spec = _read_spec(out)
    network = build_network(spec, allowed_modules)
    if network.state_dim >= 2:
        check_axes(axes, network.state_dim)
    if not jobdir.has_controller(out):
        raise CompabsError(f"{out} holds no controller ({jobdir.CONTROLLER}.json): the job ran without synthesis, "
                           "and its figures are those of a controller")
    controller = load_controller(out)
    if not isinstance(controller, Controller | ArrayController | ProductController):  # pragma: no cover
        raise CompabsError(f"{out}: {jobdir.CONTROLLER}.json is not a synthesized controller")
    initial = _initial_states(controller, spec)
    stored = _stored_starts(out, network.state_dim)
    if stored is None:
        stored = _seeded_starts(controller, spec, initial, _read_json(jobdir.report_path(out), "report"))
    starts, steps = stored
    if isinstance(controller, ProductController):
        return _draw_product(network, controller, starts, steps, initial, out, axes)
    return _draw(network, controller, starts, steps, initial, out, axes)
