"""The ``general`` case (issue 22; only when named, never under ``--quick``): the field's standard benchmarks, side by
side with SCOTS.

For each example (``examples/dcdc.yaml``, ``examples/vehicle.yaml``, ``examples/double_integrator.yaml``,
``examples/rooms.yaml``): the job end to end as ``compabs run`` runs it (:func:`bench.end_to_end.child_end_to_end`:
:func:`workers.job.run_job`, the audit beside synthesis, synthesis, closed loop, files), its abstract states,
transitions and winning domain, and the per-cell stage against the floor (the black box alone on the same samples,
:func:`bench.floor.child_floor`), printed beside SCOTS's figures (:data:`SCOTS`) and, for a linear example, beside
the exact-image-box reference (:mod:`bench.reference`: the tightest interval abstraction, its game solved
explicitly). The children are named, not imported: :func:`bench.harness.run_child` runs them.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from bench import harness
from bench.harness import Emit

#: SCOTS v0.2 (and Dionysos.jl) on the same problems, on a 2-core machine (this case does not run them again).
#: SCOTS builds the abstraction from the model (a growth bound from the ODE's Jacobian), not from data.
SCOTS: dict[str, dict[str, Any]] = {
    "dcdc": {
        "abstraction_seconds": 0.354,
        "synthesis_seconds": 0.013,
        "transitions": 3.8e6,
        "states": 800 * 799,
        "domain_states": 593_089,
        "other": "Dionysos.jl 0.76 s abstraction + 0.22 s synthesis",
        "source": "SCOTS v0.2 examples/dcdc (safety), grid 800 x 799 (its absolute rounding tolerance)",
    },
    "vehicle": {
        "abstraction_seconds": 4.97,
        "synthesis_seconds": 0.32,
        "transitions": 35.8e6,
        "states": 91_035,
        "domain_states": 48_018,
        "other": "",
        "source": "SCOTS v0.2 examples/vehicle (reach-avoid around 15 obstacles)",
    },
    "rooms": None,  # a compositional benchmark: no SCOTS run of it
}
#: The examples in the order the case runs them.
GENERAL_EXAMPLES = ("dcdc", "vehicle", "double_integrator", "rooms")
#: The linear examples, compared with their exact-image-box reference (:func:`child_reference`).
LINEAR_EXAMPLES = ("double_integrator",)
#: The examples whose subsystems are n-dimensional (2-D and 3-D): issue 22's per-cell target is about them.
N_D_EXAMPLES = ("dcdc", "vehicle")
#: Issue 22's targets ("Done when") for the general case.
GENERAL_TARGETS = {"dcdc_seconds": 60.0, "dcdc_domain_vs_scots": 0.95, "audit_transitions": 10**6, "floor": 3.0,
                   "closed_loop_runs": 100}
#: Issue 46's targets for a linear example against its exact-image-box reference: domain at least, transitions at
#: most, these shares of the reference's.
REFERENCE_TARGETS = {"domain_states": 0.9, "transitions": 1.2}


def transitions_of(subsystems: list[dict]) -> int:
    """Transitions of the subsystem relations a job built: per distinct subsystem, the non-blocking triples times
    their mean number of successors under the growth bound that built the relation."""
    total = 0
    for s in subsystems:
        key = "scp_radius" if s["growth_bound"] == "scp" and s.get("scp_objective") == "radius" else s["growth_bound"]
        mean, live = (s.get("mean_successors") or {}).get(key), (s.get("non_blocking") or {}).get(key)
        if mean is not None and live is not None:
            total += round(mean * live)
    return total


#: The examples whose games both back ends solve (single systems; the rooms are a network: BDDs only).
BACKEND_EXAMPLES = ("dcdc", "vehicle")


def child_backends(p: dict, emit: Emit) -> None:
    """One example's game on both back ends, from one abstraction (in this process, no audit): the explicit
    solver's predecessor lists and fixed points (:mod:`pipelines.synthesis.explicit`), and the BDD solver's
    relations, CPre set-up and fixed points (:func:`~pipelines.synthesis.synthesize.synthesize`), each split into
    building and fixed point; the BDDs' construction throughput (transitions per second of building the relation
    BDDs); whether the two domains are the same set of cells."""
    import numpy as np

    from pipelines.spec.model import load_spec
    from pipelines.symbolic.counting import enumerate_cells
    from pipelines.synthesis import explicit
    from pipelines.synthesis.options import SynthesisOptions
    from pipelines.synthesis.synthesize import synthesize
    from workers.job import run_abstraction

    spec = load_spec(p["spec"], p.get("set"))
    emit({"type": "stage", "stage": "abstraction"})
    ab = run_abstraction(spec, audit=False)
    network, grid = ab.network, ab.network.composed_state_grid()
    (relation,) = ab.relations.values()
    transitions = explicit.transitions(relation)
    methods = tuple(spec.options.fixed_points)
    emit({"type": "stage", "stage": "explicit"})
    game = explicit.ExplicitGame.from_relation(relation, grid.shape)
    t0 = time.perf_counter()
    results = explicit.solve(game, spec.specification, grid, methods)
    solve_seconds = time.perf_counter() - t0
    emit({"type": "row", "row": {"backend": "explicit", "build_seconds": game.build_seconds,
                                 "fixed_point_seconds": solve_seconds, "transitions": transitions,
                                 "domains": {k: r.domain_states for k, r in results.items()}}})
    emit({"type": "stage", "stage": "bdd"})
    t0 = time.perf_counter()
    cpre, bdd_results, report = synthesize(network, ab.relations, ab.interconnection, spec.specification,
                                           SynthesisOptions(reach_and_stay_methods=methods))
    total = time.perf_counter() - t0
    try:
        m = cpre.model
        same = {}
        for k, r in bdd_results.items():
            cells = enumerate_cells(m, r.domain, m.x_digits())
            mask = np.zeros(grid.size, dtype=bool)
            mask[grid.ravel(cells)] = True
            same[k] = bool(np.array_equal(mask, results[k].domain))
    finally:
        cpre.close()
    relation_seconds = sum(report["relation_seconds"].values())
    emit({"type": "row", "row": {
        "backend": "bdd", "build_seconds": report["build_seconds"], "relation_seconds": relation_seconds,
        "fixed_point_seconds": total - report["build_seconds"], "transitions": transitions,
        "transitions_per_second": harness.ratio(transitions, relation_seconds),
        "domains": {k: r.domain_states for k, r in bdd_results.items()}, "same_domains": same}})


def child_reference(p: dict, emit: Emit) -> None:
    """A linear example's exact-image-box reference (:func:`bench.reference.exact_reference`): its relation's
    transitions and its game's domain, solved explicitly."""
    from bench.reference import exact_reference
    from pipelines.spec.model import load_spec

    emit({"type": "stage", "stage": "reference"})
    emit({"type": "row", "row": exact_reference(load_spec(p["spec"], p.get("set")))})


CHILDREN = {"backends": child_backends, "reference": child_reference}


def bench_general(args: Any, *, run_child: Callable[..., dict] = harness.run_child,
                  case_record: Callable[..., dict] = harness.case_record, examples: Any = harness.EXAMPLES,
                  worker_environ: Callable[[], dict[str, str]] | None = None) -> dict:
    """Run every example end to end and its floor; the parent side of the ``general`` case (:func:`run`).

    The keywords replace the harness's own (a test's fakes); ``worker_environ`` defaults to
    :func:`workers.cluster.worker_environ`.
    """
    if worker_environ is None:
        from workers.cluster import worker_environ as default_environ

        worker_environ = default_environ
    rows: list[dict] = []
    for name in GENERAL_EXAMPLES:
        spec = examples / f"{name}.yaml"
        child = run_child("end_to_end", {"spec": str(spec), "auto": True, "workers": 2}, args.point_timeout,
                          args.mem_limit_gb * 1024)
        rec = case_record(f"general {name}", child, spec=spec.name)
        d = rec["details"]
        rec["transitions"] = transitions_of(d.get("subsystems") or [])
        floor = run_child("floor", {"spec": str(spec), "repeat": 1}, args.point_timeout, args.mem_limit_gb * 1024,
                          env=worker_environ())
        frows = [e["row"] for e in floor["events"] if e["type"] == "row"]
        rec["floor"] = {"status": floor["status"], "error": floor["error"],
                        "ratio": max((r["ratio_cpu"] for r in frows), default=None), "rows": frows,
                        "ns_per_rhs": max((r.get("ns_per_rhs_evaluation") or 0.0 for r in frows), default=None)}
        if name in BACKEND_EXAMPLES:
            both = run_child("backends", {"spec": str(spec)}, args.point_timeout, args.mem_limit_gb * 1024,
                             env=worker_environ())
            rec["backends"] = {"status": both["status"], "error": both["error"],
                               "rows": {e["row"]["backend"]: e["row"] for e in both["events"] if e["type"] == "row"}}
        if name in LINEAR_EXAMPLES:
            ref = run_child("reference", {"spec": str(spec)}, args.point_timeout, args.mem_limit_gb * 1024)
            row: dict[str, Any] = next((e["row"] for e in ref["events"] if e["type"] == "row"), {})
            rec["reference"] = {"status": ref["status"], "error": ref["error"], "row": row}
            rec["vs_reference"] = {"domain_states": harness.ratio(rec["domain_states"], row.get("domain_states")),
                                   "transitions": harness.ratio(rec["transitions"], row.get("transitions"))}
        scots = SCOTS.get(name)
        rec["scots"] = scots
        if scots:
            rec["vs_scots"] = {
                "domain_states": harness.ratio(rec["domain_states"], scots["domain_states"]),
                "transitions": harness.ratio(rec["transitions"], scots["transitions"]),
                "subsystems_seconds": harness.ratio(rec["stages"].get("subsystems", {}).get("wall"),
                                                    scots["abstraction_seconds"]),
            }
        rows.append(rec)
    return {"case": "general", "status": "ok" if all(r["status"] == "ok" for r in rows) else "error",
            "error": "; ".join(f"{r['case']}: {r['error']}" for r in rows if r.get("error")) or None,
            "runs": rows, "peak_rss_mb": max((r["peak_rss_mb"] for r in rows), default=None),
            "others_cores": max((r["others_cores"] for r in rows), default=None),
            # Issue 22's criterion is about the n-D examples; the rooms' subsystems are scalar (their row is printed).
            "ratio": max((r["floor"]["ratio"] or 0.0 for r in rows if r["case"].split()[-1] in N_D_EXAMPLES),
                         default=None)}


def run(args: Any) -> dict:
    """The case for ``bench/run.py --cases general``."""
    rec = bench_general(args)
    harness.baseline_progress(rec)
    return rec


def lines(c: dict) -> list[str]:
    """The case's lines in the table: a heading and :func:`general_lines`."""
    return ["  general: the field's benchmarks beside SCOTS (examples/dcdc, vehicle, double_integrator, rooms)",
            *general_lines(c)]


def targets(c: dict, put: harness.Put) -> None:
    """The case's targets in the table: :func:`general_targets`."""
    general_targets(c, put)


def general_lines(c: dict, fmt: Callable[..., str] = harness.fmt) -> list[str]:
    """The general case's table: ours beside SCOTS's per example."""
    w = max([9, *(len(r["case"].split()[-1]) + 1 for r in c["runs"])])  # the first column fits every name
    out = [f"  {'example':<{w}}{'states':>11}{'transitions':>13}{'domain':>11}{'end-to-end s':>14}{'per-cell s':>12}"
           f"{'/floor':>8}{'ns/rhs':>8}{'audit':>10}{'viol.':>6}{'runs':>6}{'viol.':>6}   SCOTS (states, transitions, domain, s)"]
    for r in c["runs"]:
        d = r["details"]
        audit, loop = d.get("audit") or {}, d.get("closed_loop") or {}
        s = r.get("scots") or {}
        scots = (f"{fmt(s.get('states'))}, {fmt(s.get('transitions'))}, {fmt(s.get('domain_states'))}, "
                 f"{fmt(s.get('abstraction_seconds'))}" if s else "-")
        out.append(f"  {r['case'].split()[-1]:<{w}}{fmt(r['abstract_states']):>11}{fmt(r['transitions']):>13}"
                   f"{fmt(r['domain_states']):>11}{fmt(r['total_wall']):>14}"
                   f"{fmt(r['stages'].get('subsystems', {}).get('wall')):>12}{fmt(r['floor']['ratio']):>8}"
                   f"{fmt(r['floor'].get('ns_per_rhs')):>8}"
                   f"{fmt(audit.get('transitions_checked')):>10}{fmt(audit.get('violations')):>6}"
                   f"{fmt(loop.get('runs')):>6}{fmt(loop.get('violations')):>6}   {scots}")
    out.append(f"  {'synthesis':<{w}}{'explicit: build s':>19}{'fixed pt s':>12}{'BDD: build s':>14}{'relations s':>13}"
               f"{'fixed pt s':>12}{'BDD trans/s':>13}{'same domain':>13}   SCOTS synthesis s")
    for r in c["runs"]:
        both = (r.get("backends") or {}).get("rows") or {}
        if not both:
            continue
        e, b = both.get("explicit") or {}, both.get("bdd") or {}
        same = b.get("same_domains") or {}
        out.append(f"  {r['case'].split()[-1]:<{w}}{fmt(e.get('build_seconds')):>19}{fmt(e.get('fixed_point_seconds')):>12}"
                   f"{fmt(b.get('build_seconds')):>14}{fmt(b.get('relation_seconds')):>13}"
                   f"{fmt(b.get('fixed_point_seconds')):>12}{fmt(b.get('transitions_per_second')):>13}"
                   f"{('yes' if same and all(same.values()) else 'NO' if same else '-'):>13}"
                   f"   {fmt((r.get('scots') or {}).get('synthesis_seconds'))}")
    refs = [r for r in c["runs"] if r.get("reference")]
    if refs:
        out.append(f"  {'reference':<{w}}{'exact image boxes: transitions':>32}{'domain':>11}{'ours / ref.: transitions':>26}"
                   f"{'domain':>9}")
    for r in refs:
        row, vs = r["reference"].get("row") or {}, r.get("vs_reference") or {}
        out.append(f"  {r['case'].split()[-1]:<{w}}{fmt(row.get('transitions')):>32}{fmt(row.get('domain_states')):>11}"
                   f"{fmt(vs.get('transitions')):>26}{fmt(vs.get('domain_states')):>9}"
                   + (f"   {r['reference']['error']}" if r["reference"].get("error") else ""))
    return out


def general_targets(c: dict, put: harness.Put) -> None:
    """Issue 22's "Done when" checks, through ``put(name, value, target, ok)``."""
    runs = {r["case"].split()[-1]: r for r in c["runs"]}
    dc = runs.get("dcdc")
    if dc:
        d = dc["details"]
        audit, loop = d.get("audit") or {}, d.get("closed_loop") or {}
        ok = dc["status"] == "ok" and dc["total_wall"] <= GENERAL_TARGETS["dcdc_seconds"]
        put("dcdc end to end s", dc["total_wall"], f"<= {GENERAL_TARGETS['dcdc_seconds']}", ok)
        share = harness.ratio(dc["domain_states"], SCOTS["dcdc"]["domain_states"])
        put("dcdc domain / SCOTS", share, f">= {GENERAL_TARGETS['dcdc_domain_vs_scots']}",
            share is not None and share >= GENERAL_TARGETS["dcdc_domain_vs_scots"])
        put("dcdc audit transitions (violations)", audit.get("transitions_checked"), ">= 1e6, 0 violations",
            (audit.get("transitions_checked") or 0) >= GENERAL_TARGETS["audit_transitions"]
            and audit.get("violations") == 0 and loop.get("violations") == 0)
    ve = runs.get("vehicle")
    if ve:
        loop = ve["details"].get("closed_loop") or {}
        put("vehicle closed-loop runs (violations)", loop.get("runs"), ">= 100, 0 violations",
            (loop.get("runs") or 0) >= GENERAL_TARGETS["closed_loop_runs"] and loop.get("violations") == 0)
    for name in LINEAR_EXAMPLES:
        vs = (runs.get(name) or {}).get("vs_reference")
        if vs is None:
            continue
        share, more = vs.get("domain_states"), vs.get("transitions")
        put(f"{name} domain / exact-image reference", share, f">= {REFERENCE_TARGETS['domain_states']}",
            share is not None and share >= REFERENCE_TARGETS["domain_states"])
        put(f"{name} transitions / exact-image reference", more, f"<= {REFERENCE_TARGETS['transitions']}",
            more is not None and more <= REFERENCE_TARGETS["transitions"])
    worst = c.get("ratio")
    put("per-cell / floor (worst of the 2-D, 3-D)", worst, f"<= {GENERAL_TARGETS['floor']}",
        worst is not None and worst <= GENERAL_TARGETS["floor"])
