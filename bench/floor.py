"""The ``floor`` case (a): the per-cell stage against the bare evaluation of its black box.

The per-cell stage (``abstract_cells`` over the default chunks of each distinct subsystem) against the floor: the
compiled dynamics (``compile_expression``, no validation) evaluated on exactly the sample arrays that stage
evaluated (recorded from it), chunk by chunk. Ratio = stage CPU / floor CPU, the worst subsystem's. The stage runs
in a Dask worker, so both are measured in a process with a worker's environment (``workers/dask.yaml``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any, cast

from bench.harness import (
    EXAMPLES,
    Emit,
    Put,
    Recorder,
    baseline,
    baseline_lines,
    case_record,
    given_constants,
    limits,
    ratio,
    run_child,
    with_samples,
)

#: Issue 6's target: per-cell stage / floor, worst subsystem.
TARGET = 3.0


# ====================================================================================== child side
def floor_function(sub: Any, network: Any) -> tuple[Callable, Callable]:
    """The compiled dynamics of a subsystem, called bare (no shape or finiteness checks), and how to turn the
    recorded arguments of a sample call into its arguments (outside the timing).

    An expression reads the recorded broadcast views as they are; a ``module:function`` gets the ``(B, d)`` copies
    the black box would make for it (making them is the stage's work, not the floor's).
    """
    import numpy as np

    from pipelines.expressions import compile_expression
    from pipelines.spec.model import is_module_function

    if getattr(sub.spec, "ode", None):
        # An ODE: the black box is the integrator over the right-hand side; the floor is that integration alone.
        return (lambda *arrays: sub.dynamics(*arrays)), (lambda arrays: arrays)
    src = sub.spec.dynamics
    names = list(sub.dynamics.inputs)  # x, u, w in call order
    if is_module_function(src):
        import importlib

        mod, fn = src.split(":")

        from pipelines.blackbox import as_rows

        def flat(arrays):
            return as_rows(arrays, np.broadcast_shapes(*(a.shape[:-1] for a in arrays)))

        return getattr(importlib.import_module(mod), fn), flat
    used = {k: d for k, d in sub.dynamics.inputs.items() if d > 0}
    expr = compile_expression(src, used, network.constants)

    def bare(*arrays):
        return expr(**{k: np.moveaxis(a, -1, 0) for k, a in zip(names, arrays) if k in used})

    return bare, lambda arrays: arrays


def child_floor(p: dict, emit: Emit) -> None:
    """(a) Per-cell stage against the bare evaluation of the black box on the same samples: one row per distinct
    subsystem, the best (least CPU) of ``p['repeat']`` passes."""
    import pipelines.abstraction.kernels as compiled
    from pipelines.abstraction.cells import abstract_cells
    from pipelines.abstraction.relation import chunk_ranges
    from pipelines.network import build_network
    from pipelines.spec.model import load_spec

    compiled.warm_up()  # numba compiles (or loads its cache) at the first call: not the stage's work
    spec = load_spec(p["spec"], p.get("set"))
    if p.get("samples"):
        spec = with_samples(spec, p["samples"], p.get("input_eta"))
    network = build_network(spec, None)
    for members in network.unique_subsystems().values():
        sub = members[0]
        L_x, L_w = given_constants(sub)
        chunks = chunk_ranges(sub, spec.options.chunk_cells)
        floor, prepare = floor_function(sub, network)
        best: dict[str, Any] | None = None
        for _ in range(p.get("repeat", 1)):
            tot = {"stage_wall": 0.0, "stage_cpu": 0.0, "floor_wall": 0.0, "floor_cpu": 0.0, "evaluations": 0}
            for a, b in chunks:
                rec = Recorder(sub.dynamics)
                s2 = replace(sub, dynamics=cast(Any, rec))
                w0, c0 = time.perf_counter(), time.process_time()
                abstract_cells(s2, a, b, L_x, L_w, sub.spec.growth_bound, sub.spec.scp_objective)
                w1, c1 = time.perf_counter(), time.process_time()
                calls = [prepare(args) for args, _ in rec.calls]
                w2, c2 = time.perf_counter(), time.process_time()
                for args in calls:
                    floor(*args)
                w3, c3 = time.perf_counter(), time.process_time()
                tot["stage_wall"] += w1 - w0
                tot["stage_cpu"] += c1 - c0
                tot["floor_wall"] += w3 - w2
                tot["floor_cpu"] += c3 - c2
                tot["evaluations"] += sum(out.shape[0] * out.shape[1] * out.shape[2] for _, out in rec.calls)
                del rec, s2
            if best is None or tot["stage_cpu"] + tot["floor_cpu"] < best["stage_cpu"] + best["floor_cpu"]:
                best = tot
        assert best is not None
        best.update(subsystem=sub.name, members=len(members), chunks=len(chunks), triples=sub.triples,
                    ratio_cpu=best["stage_cpu"] / best["floor_cpu"], ratio_wall=best["stage_wall"] / best["floor_wall"],
                    ns_per_evaluation_stage=1e9 * best["stage_cpu"] / best["evaluations"],
                    ns_per_evaluation_floor=1e9 * best["floor_cpu"] / best["evaluations"],
                    # an ODE's black-box evaluation is 4 x substeps right-hand-side evaluations (RK4)
                    ns_per_rhs_evaluation=1e9 * best["floor_cpu"] / (best["evaluations"] * sub.spec.rhs_evaluations))
        emit({"type": "row", "row": best})


CHILDREN = {"floor": child_floor}


# ====================================================================================== parent side
def run(args: Any) -> dict:
    """Each spec's subsystems in a child with a Dask worker's environment; the ratio of the worst."""
    from workers.cluster import worker_environ

    if args.quick:
        specs: list[tuple[Path, dict[str, Any]]] = [(EXAMPLES / "small.yaml", {}), (EXAMPLES / "tanks.yaml", {})]
    else:
        specs = [(EXAMPLES / "tanks.yaml", {}), (EXAMPLES / "consensus.yaml", {}),
                 (EXAMPLES / "scalability.yaml", {}), (EXAMPLES / "stress.yaml", {"repeat": 1})]
    rows, children = [], []
    for spec, extra in specs:
        child = run_child("floor", {"spec": str(spec), "repeat": 3, **extra}, *limits(args), env=worker_environ())
        children.append(case_record(f"floor {spec.stem}", child, spec=spec.name))
        for e in child["events"]:
            if e["type"] == "row":
                rows.append({"spec": spec.name, **e["row"]})
    stage = sum(r["stage_cpu"] for r in rows)
    floor = sum(r["floor_cpu"] for r in rows)
    worst = max(rows, key=lambda r: r["ratio_cpu"]) if rows else None
    return baseline("floor", children, rows=rows, ratio=max((r["ratio_cpu"] for r in rows), default=None),
                    ratio_meaning="per-cell stage CPU / bare evaluation CPU, worst subsystem (target <= 3)",
                    ratio_pooled=ratio(stage, floor), worst=worst and f"{worst['spec']}:{worst['subsystem']}")


# ====================================================================================== table and targets
def lines(c: dict) -> list[str]:
    return baseline_lines("floor", c, [
        f"    {r['spec']}:{r['subsystem']:<8} stage {r['stage_cpu']:.3f} s, floor {r['floor_cpu']:.3f} s CPU, "
        f"{r['evaluations']:.3g} evaluations ({r['ns_per_evaluation_stage']:.0f} vs "
        f"{r['ns_per_evaluation_floor']:.0f} ns each, {r.get('ns_per_rhs_evaluation', 0):.1f} ns per right-hand side): "
        f"{r['ratio_cpu']:.2f}x (wall {r['ratio_wall']:.2f}x)"
        for r in c["rows"]])


def targets(c: dict, put: Put) -> None:
    v = c["ratio"]
    put("per-cell / floor (worst)", v, f"<= {TARGET}", v is not None and v <= TARGET)
