"""The ``scp`` case (b): the batched exact SCP against one LP per cell, on the pipeline's own samples.

The batched exact SCP as the stage runs it (:mod:`pipelines.abstraction.kernels`: sample extremes, pair maxima,
closed-form SCP, all cells of a subsystem; the numpy batch ``pair_maxima_scalar`` + ``scp_parameters_scalar`` is
timed beside it and must give the same bits) against the reference formulation (``scp_reference``: one HiGHS LP
over all sample pairs per cell, a random subset of cells). Per objective (``paper``, ``radius``): the speed ratio
per cell, the largest difference of objective values and of radii.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

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
    run_child,
)

#: Issue 6's targets: the batched SCP at least this much faster than the LP, and agreeing to within this.
TARGETS = {"scp_speedup": 30.0, "scp_agreement": 1e-9}
OBJECTIVES = ("paper", "radius")


# ====================================================================================== child side
def _samples(sub: Any, spec: Any, L_x: float, L_w: float) -> tuple[Any, ...]:
    """The samples and successors the pipeline uses, recorded from ``abstract_cells`` chunk by chunk, with each
    triple's half-width, sub-grid spacing and ``rho``: ``(X, V, RX, HX, rho, S_x, S_w)``, triples first."""
    import numpy as np

    from pipelines.abstraction.cells import abstract_cells
    from pipelines.abstraction.growth_bound import scp_rho, subgrid_counts
    from pipelines.abstraction.relation import chunk_ranges

    xg, wg = sub.state_grid, sub.internal_grid
    counts = subgrid_counts(sub.spec.samples, sub.n + sub.p)
    cx, cw = counts[: sub.n], counts[sub.n:]
    Sx, Sw = int(np.prod(cx)), int(np.prod(cw)) if cw else 1
    Xs, Vs, RXs, HXs, rhos = [], [], [], [], []
    n_u = sub.input_grid.size
    if wg is None:
        w_lo = w_hi = np.zeros((1, 0))
    else:
        w_lo, w_hi = wg.clipped_cells(wg.unravel(np.arange(wg.size)))
    n_w = w_lo.shape[0]
    for a, b in chunk_ranges(sub, spec.options.chunk_cells):
        rec = Recorder(sub.dynamics)
        abstract_cells(replace(sub, dynamics=rec), a, b, L_x, L_w, "scp", "paper")
        c = b - a
        B = c * n_u * n_w
        # abstract_cells lays each block's samples out sample-major, (S_x, S_w, triples): triples first here.
        for args, out in rec.calls:  # args[0]: (Sx, 1, Bb, n) state samples, broadcast over the w samples
            Bb = out.shape[2]
            Xs.append(np.moveaxis(np.broadcast_to(args[0], (Sx, Sw, Bb, sub.n)).reshape(Sx * Sw, Bb, sub.n), 1, 0))
            Vs.append(np.moveaxis(out.reshape(Sx, Sw, Bb, sub.n), 2, 0))
        x_lo, x_hi = xg.clipped_cells(xg.unravel(np.arange(a, b)))
        RX = np.broadcast_to(((x_hi - x_lo) / 2)[:, None, None, :], (c, n_u, n_w, sub.n)).reshape(B, sub.n)
        RW = np.broadcast_to(((w_hi - w_lo) / 2)[None, None, :, :], (c, n_u, n_w, sub.p)).reshape(B, sub.p)
        HX = 2 * RX / np.asarray(cx, dtype=float)
        HW = 2 * RW / np.asarray(cw, dtype=float) if sub.p else RW
        RXs.append(RX)
        HXs.append(HX)
        rhos.append(scp_rho(HX, HW, L_x, L_w))
    X, V, RX, HX, rho = (np.concatenate(v) for v in (Xs, Vs, RXs, HXs, rhos))
    return X, V, RX, HX, rho, Sx, Sw


def child_scp(p: dict, emit: Emit) -> None:
    """(b) Batched exact SCP against one HiGHS LP per cell, on the pipeline's own samples."""
    import numpy as np

    import pipelines.abstraction.kernels as compiled
    from pipelines.abstraction.growth_bound import (
        SCP_TIE_RTOL,
        pair_maxima_scalar,
        scp_parameters_scalar,
        scp_reference,
    )
    from pipelines.network import build_network
    from pipelines.spec.model import load_spec

    spec = load_spec(p["spec"], p.get("set"))
    network = build_network(spec, None)
    sub = next(iter(network.unique_subsystems().values()))[0]
    if sub.n != 1:
        raise ValueError("the batched SCP is for scalar states")
    L_x, L_w = given_constants(sub)
    X, V, RX, HX, rho, Sx, Sw = _samples(sub, spec, L_x, L_w)
    B = V.shape[0]
    rng = np.random.default_rng(0)
    subset = np.sort(rng.choice(B, size=min(B, p["reference_cells"]), replace=False))
    out: dict[str, Any] = {"subsystem": sub.name, "spec": Path(p["spec"]).name, "cells": B,
                           "reference_cells": int(subset.size), "samples_per_cell": Sx * Sw,
                           "pairs_per_lp": Sx * Sw * (Sx * Sw + 1) // 2}
    # The stage's layout (samples first, cells on the contiguous axis) and its compiled kernels; the numpy
    # batch (pipelines.abstraction.growth_bound, the kernels' reference) is timed beside them.
    compiled.warm_up()
    Vt = np.ascontiguousarray(np.moveaxis(V[..., 0], 0, -1).reshape(Sx, Sw, B))
    for objective in OBJECTIVES:
        weight = np.ones(B) if objective == "paper" else RX[:, 0]
        best = best_numpy = math.inf
        for _ in range(p.get("repeat", 3)):
            c0 = time.process_time()
            vmax, vmin, _, _ = compiled.scalar_sample_pass(Vt)
            E = compiled.pair_maxima_batch_last(vmax, vmin)
            t1, t2 = compiled.scp_parameters_batch_last(E, HX[:, 0], rho, L_x, weight, SCP_TIE_RTOL)
            c1 = time.process_time()
            E = pair_maxima_scalar(V[..., 0])
            n1, n2 = scp_parameters_scalar(E, HX[:, 0], rho, L_x, weight)
            best, best_numpy = min(best, c1 - c0), min(best_numpy, time.process_time() - c1)
        if not (np.array_equal(t1, n1) and np.array_equal(t2, n2)):
            raise AssertionError("the compiled SCP differs from its numpy reference")
        c0 = time.process_time()
        ref = [scp_reference(X[k], V[k].reshape(-1, sub.n), float(rho[k]), L_x, np.array([weight[k]])) for k in subset]
        ref_cpu = time.process_time() - c0
        th1 = np.array([r[0][0, 0] for r in ref])
        th2 = np.array([r[1][0] for r in ref])
        obj_fast = weight[subset] * t1[subset] + t2[subset]
        obj_ref = weight[subset] * th1 + th2
        rad_fast = t1[subset] * RX[subset, 0] + t2[subset]
        rad_ref = th1 * RX[subset, 0] + th2
        per_fast, per_ref = best / B, ref_cpu / subset.size
        out[objective] = {
            "batched_cpu_per_cell": per_fast, "reference_cpu_per_cell": per_ref, "speedup": per_ref / per_fast,
            "batched_numpy_cpu_per_cell": best_numpy / B,
            "max_objective_difference": float(np.max(np.abs(obj_fast - obj_ref))),
            "max_radius_difference": float(np.max(np.abs(rad_fast - rad_ref))),
            "cells_radius_differs_1e-9": int(np.sum(np.abs(rad_fast - rad_ref) > 1e-9)),
            "max_relative_radius_difference": float(np.max(np.abs(rad_fast - rad_ref) / np.maximum(rad_ref, 1e-300))),
        }
    emit({"type": "row", "row": out})


CHILDREN = {"scp": child_scp}


# ====================================================================================== parent side
def run(args: Any) -> dict:
    """Each spec's first distinct subsystem in a child; the smallest speed-up and the largest differences."""
    if args.quick:
        specs = [(EXAMPLES / "small.yaml", 20)]
    else:
        specs = [(EXAMPLES / "consensus.yaml", 150), (EXAMPLES / "scalability.yaml", 150)]
    rows, children = [], []
    for spec, k in specs:
        child = run_child("scp", {"spec": str(spec), "reference_cells": k}, *limits(args))
        children.append(case_record(f"scp {spec.stem}", child, spec=spec.name))
        rows += [e["row"] for e in child["events"] if e["type"] == "row"]
    sp = [r[o]["speedup"] for r in rows for o in OBJECTIVES]
    return baseline("scp", children, rows=rows, ratio=min(sp) if sp else None,
                    ratio_meaning="reference LP CPU per cell / batched CPU per cell, smallest (target >= 30)",
                    max_objective_difference=max((r[o]["max_objective_difference"] for r in rows
                                                  for o in OBJECTIVES), default=None),
                    max_radius_difference=max((r[o]["max_radius_difference"] for r in rows
                                               for o in OBJECTIVES), default=None),
                    max_radius_difference_radius_objective=max((r["radius"]["max_radius_difference"] for r in rows),
                                                               default=None))


# ====================================================================================== table and targets
def lines(c: dict) -> list[str]:
    return baseline_lines("scp", c, [
        f"    {r['spec']}:{r['subsystem']} objective {o}: {1e6 * q['batched_cpu_per_cell']:.2f} us "
        f"(numpy {1e6 * q['batched_numpy_cpu_per_cell']:.2f} us) vs "
        f"{1e3 * q['reference_cpu_per_cell']:.1f} ms per cell ({r['cells']} / {r['reference_cells']} cells)"
        f" -> {q['speedup']:.0f}x; max |d objective| {q['max_objective_difference']:.1e}, "
        f"max |d radius| {q['max_radius_difference']:.1e}"
        for r in c["rows"] for o in OBJECTIVES for q in (r[o],)])


def targets(c: dict, put: Put) -> None:
    v = c["ratio"]
    put("batched SCP speed-up (least)", v, f">= {TARGETS['scp_speedup']:.0f}", v is not None and v >= TARGETS["scp_speedup"])
    for key, name in (("max_objective_difference", "objective"), ("max_radius_difference", "radius")):
        d = c[key]
        put(f"batched SCP |d {name}|", d, f"<= {TARGETS['scp_agreement']}", d is not None and d <= TARGETS["scp_agreement"])
