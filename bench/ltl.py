"""The ``ltl`` case (issue 48; only when named; under ``--quick`` the robot alone): temporal-logic tasks on both back
ends.

For each example (``examples/robot_ltl.yaml``, ``examples/vehicle_ltl.yaml``), from one abstraction (in the child's
process, no audit): the formula's automaton (MONA, :func:`workers.automata.spec_automaton`: its states, atoms and
accepting states), the product game on the explicit back end (the predecessor lists, then
:func:`~pipelines.synthesis.product.reach_explicit`) and on the BDD back end
(:func:`~pipelines.synthesis.synthesize.synthesize` with the automaton: the relations and CPre, then
:func:`~pipelines.synthesis.product.reach_symbolic`), each split into building and the fixed point; the product's
size (automaton states × cells) and winning product states; whether both back ends win the same product states and
the same domain, cell by cell.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from bench import harness
from bench.harness import Emit

#: The examples in the order the case runs them; ``--quick`` runs the first.
LTL_EXAMPLES = ("robot_ltl", "vehicle_ltl")


def child_ltl(p: dict, emit: Emit) -> None:
    """One example's product game on both back ends (module docstring); one ``row`` event per back end."""
    import numpy as np

    from pipelines.spec.model import load_spec
    from pipelines.symbolic.counting import enumerate_cells
    from pipelines.synthesis.explicit import ExplicitGame
    from pipelines.synthesis.options import SynthesisOptions
    from pipelines.synthesis.product import reach_explicit
    from pipelines.synthesis.synthesize import synthesize
    from pipelines.temporal.labels import Labelling
    from workers.automata import spec_automaton
    from workers.job import run_abstraction

    clock = [time.perf_counter(), time.process_time()]

    def stage(name: str) -> None:
        """The stage that just ended, with its wall and CPU seconds (the harness's stage records)."""
        now = [time.perf_counter(), time.process_time()]
        emit({"type": "stage", "stage": name, "wall": now[0] - clock[0], "cpu": now[1] - clock[1]})
        clock[:] = now

    spec = load_spec(p["spec"], p.get("set"))
    ab = run_abstraction(spec, audit=False)
    network, grid = ab.network, ab.network.composed_state_grid()
    stage("abstraction")
    t0 = time.perf_counter()
    automaton = spec_automaton(spec.specification, spec.options.max_automaton_states)
    size = {**automaton.summary(), "seconds": time.perf_counter() - t0, "cells": grid.size,
            "product_states": automaton.n_states * grid.size}
    stage("automaton")
    (relation,) = ab.relations.values()
    game = ExplicitGame.from_relation(relation, grid.shape)
    t0 = time.perf_counter()
    labelling = Labelling.of(automaton.atoms, spec.specification.regions or {}, grid)
    classes, cell_class = np.unique(labelling.classes(grid.unravel(np.arange(game.n_x))), return_inverse=True)
    explicit = reach_explicit(game, automaton, cell_class.reshape(-1), labelling.class_letters(classes))
    solve = time.perf_counter() - t0
    emit({"type": "row", "row": {"backend": "explicit", "build_seconds": game.build_seconds,
                                 "fixed_point_seconds": solve, "iterations": explicit.iterations,
                                 "winning_product_states": int(explicit.winning.sum()),
                                 "domain_states": explicit.domain_states, "automaton": size}})
    stage("explicit")
    t0 = time.perf_counter()
    cpre, results, report = synthesize(network, ab.relations, ab.interconnection, spec.specification,
                                       SynthesisOptions(automaton=automaton))
    total = time.perf_counter() - t0
    product = results["ltl"]
    try:
        m = cpre.model

        def mask(f: Any) -> np.ndarray:
            out = np.zeros(grid.size, dtype=bool)
            out[grid.ravel(enumerate_cells(m, f, m.x_digits()))] = True
            return out

        same_winning = all(np.array_equal(mask(w), explicit.winning[q]) for q, w in enumerate(product.winning))
        same_domain = bool(np.array_equal(mask(product.domain), explicit.domain))
    finally:
        cpre.close()
    stage("bdd")
    emit({"type": "info", "abstract_states": grid.size, "domain_states": product.domain_states})
    emit({"type": "row", "row": {
        "backend": "bdd", "build_seconds": report["build_seconds"], "fixed_point_seconds": total - report["build_seconds"],
        "iterations": product.iterations, "winning_product_states": product.details["winning_product_states"],
        "domain_states": product.domain_states, "same_winning": same_winning, "same_domain": same_domain}})


CHILDREN = {"ltl": child_ltl}


def bench_ltl(args: Any, *, run_child: Callable[..., dict] = harness.run_child,
              examples: Any = harness.EXAMPLES) -> dict:
    """Run :func:`child_ltl` per example (the robot alone under ``--quick``); the parent side of the case."""
    rows = []
    for name in LTL_EXAMPLES[:1] if args.quick else LTL_EXAMPLES:
        spec = examples / f"{name}.yaml"
        child = run_child("ltl", {"spec": str(spec)}, args.point_timeout, args.mem_limit_gb * 1024)
        rec = harness.case_record(f"ltl {name}", child, spec=spec.name)
        rec["backends"] = {e["row"]["backend"]: e["row"] for e in child["events"] if e["type"] == "row"}
        rows.append(rec)
    return {"case": "ltl", "status": "ok" if all(r["status"] == "ok" for r in rows) else "error",
            "error": "; ".join(f"{r['case']}: {r['error']}" for r in rows if r.get("error")) or None, "runs": rows}


def run(args: Any) -> dict:
    """The case for ``bench/run.py --cases ltl``."""
    rec = bench_ltl(args)
    harness.baseline_progress(rec)
    return rec


def lines(c: dict, fmt: Callable[..., str] = harness.fmt) -> list[str]:
    """The case's table: per example the automaton, the product and each back end's times."""
    out = ["  ltl: temporal-logic tasks, the product game on both back ends (build s + fixed point s)"]
    for r in c["runs"]:
        e, b = r["backends"].get("explicit"), r["backends"].get("bdd")
        if e is None or b is None:
            out.append(f"    {r['case']}: {r['status']} {r.get('error') or ''}")
            continue
        a = e["automaton"]
        same = "same" if b["same_winning"] and b["same_domain"] else "DIFFERENT"
        out.append(f"    {r['case']}: automaton {a['states']} states, {len(a['atoms'])} atoms ({a['letters']} letters, "
                   f"{a['accepting_states']} accepting, MONA {fmt(a['seconds'])} s); product {a['states']} x "
                   f"{a['cells']:,} = {a['product_states']:,}, {e['winning_product_states']:,} winning, domain "
                   f"{e['domain_states']:,} cells")
        out.append(f"      explicit {fmt(e['build_seconds'])} + {fmt(e['fixed_point_seconds'])} s, bdd "
                   f"{fmt(b['build_seconds'])} + {fmt(b['fixed_point_seconds'])} s, {e['iterations']} iterations; "
                   f"winning product states and domains {same} on both")
    return out


def targets(c: dict, put: harness.Put) -> None:
    """Issue 48: both back ends win the same product states and the same domain on every example."""
    rows = [r["backends"].get("bdd") or {} for r in c["runs"]]
    same = all(r.get("same_winning") and r.get("same_domain") for r in rows) if rows else None
    put("ltl same product on both back ends", same, "True", bool(same))
