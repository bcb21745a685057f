"""The control stages of a job: synthesis, the controller's files, the closed loop and the figures.

Called by the orchestrator (:func:`workers.job.run_job`) after the abstraction stages. Synthesis runs in this
process (one CUDD manager per process); with ``options.synthesis_processes`` above one, the partitioned
``∃u.CPre`` runs in helper processes (:mod:`workers.processes.partitioned_cpre`), which are this module's to
start and stop.
"""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np

from pipelines.controller import controller_of
from pipelines.figures import domain_slice_figure, trajectory_figure
from pipelines.spec.regions import spec_regions
from pipelines.synthesis.synthesize import synthesize
from pipelines.verification.closed_loop import run_closed_loop, simulate
from workers import jobdir
from workers.processes.partitioned_cpre import PartitionedPredecessors
from workers.stages import Abstraction, Progress, no_progress


def run_synthesis(
    abstraction: Abstraction,
    out_dir: str | os.PathLike[str] | None = None,
    *,
    progress: Progress = no_progress,
    runs: int | None = None,
) -> dict[str, Any]:
    """Synthesize, save the controller, run the closed loop and draw the figures (METHOD §5-6).

    Parameters
    ----------
    abstraction : Abstraction
    out_dir : path, optional
        The job directory to write the controller files, figures and example run into (none if ``None``).
    runs : int, optional
        Closed-loop runs from random domain states (default: ``options.closed_loop_runs``).

    Returns
    -------
    dict
        The report entries ``domain_states``, ``domain_states_by_fixed_point``, ``controller``, ``synthesis``,
        ``closed_loop``, ``figures`` and ``stage_seconds``.
    """
    spec = abstraction.spec
    opts = spec.options
    kind = spec.specification.kind
    network = abstraction.network
    t0 = time.perf_counter()
    progress("synthesis", 0, 1, "building BDDs and solving")
    cpre, results, syn_report = synthesize(
        network, abstraction.relations, abstraction.interconnection, spec.specification,
        reach_and_stay_methods=tuple(opts.fixed_points), processes=opts.synthesis_processes,
        partitioned=PartitionedPredecessors,
    )
    progress("synthesis", 1, 1, ", ".join(f"{k}: {r.domain_states}" for k, r in results.items()))
    seconds = {"synthesis": time.perf_counter() - t0}
    main_key = opts.controller if kind == "reach_and_stay" else next(iter(results))
    main = results[main_key]

    meta = {
        "kind": kind,
        "fixed_point": main_key,
        "state_grid": network.composed_state_grid().describe(),
        "input_grids": [s.input_grid.describe() for s in network.subsystems],
        "spec": spec.model_dump(mode="json"),
        "domain_states": main.domain_states,
    }
    controller = controller_of(cpre, main, meta)
    files: list[str] = []
    if out_dir is not None:
        files = [p.name for p in controller.save(out_dir, jobdir.CONTROLLER)]
        for key, r in results.items():
            if key != main_key:
                controller_of(cpre, r, {**meta, "fixed_point": key, "domain_states": r.domain_states}).save(
                    out_dir, f"{jobdir.CONTROLLER}_{key}"
                )

    # Closed loop (Theorem 4.2): from the spec's initial states in the domain, and from random domain states.
    t0 = time.perf_counter()
    rng = np.random.default_rng(opts.seed + 1)
    steps = opts.closed_loop_steps or (2 * (main.iterations + main.inner_iterations) + 30)
    regions = spec_regions(spec, network)
    target = regions.get("target") or regions.get("safe")
    avoid = regions.get("avoid")
    loop = run_closed_loop(
        network, controller, opts.initial_states, opts.closed_loop_runs if runs is None else runs, steps, rng, kind,
        target, avoid, progress=lambda k, n: progress("closed_loop", k, n, "runs in lockstep"),
    )
    seconds["closed_loop"] = time.perf_counter() - t0

    figures = []
    if out_dir is not None and loop.runs:
        grid = network.composed_state_grid()
        _, x0, run = loop.runs[0]
        free = simulate(network, None, x0, run.inputs.shape[0] or steps, rng, kind, target, avoid)
        band = None
        target_spec = spec.specification.target
        if kind in ("reach_and_stay", "reach", "reach_avoid"):
            assert target_spec is not None  # SpecificationSpec requires a target for these kinds
            if target_spec.boxes:
                b = target_spec.boxes[0]
                lb, ub = np.atleast_1d(b.lb), np.atleast_1d(b.ub)
                band = (float(lb.min()), float(ub.max()))
        title = f"{spec.name} from {np.round(x0, 1).tolist()}"
        figures.append(trajectory_figure(run, free, jobdir.figure(out_dir, "trajectory"), title, band).name)
        idx = controller.cell(x0)
        if grid.dim >= 2 and idx is not None:
            figures.append(domain_slice_figure(
                controller.in_domain, grid.axis_points(0), grid.axis_points(1), idx, 0, 1,
                jobdir.figure(out_dir, "domain_slice"), f"{spec.name}: domain on (x1, x2), others at the cell of x0",
            ).name)
        jobdir.write_example_run(out_dir, {"controlled": run.as_dict(), "free": free.as_dict()})

    return {
        "domain_states": main.domain_states,
        "domain_states_by_fixed_point": {k: r.domain_states for k, r in results.items()},
        "controller": {"fixed_point": main_key, "form": "layered" if main.layers else "explicit",
                       "nodes": controller.nodes, "files": files},
        "synthesis": syn_report,
        "closed_loop": loop.summary(),
        "figures": figures,
        "stage_seconds": seconds,
    }
