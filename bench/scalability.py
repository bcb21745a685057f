"""The ``scalability`` case: the paper's Fig. 3 series, ``examples/scalability.yaml --set N=...``.

For N = 4 ... 1024, doubling (``--quick``: 4, 8, 16): the abstraction stages (audit off, as in the paper's Fig. 3)
and the composition, i.e. building the symbolic model from the abstraction (``ControllablePredecessor.from_network``:
subsystem relations, interconnection relation, CPre set-up; not the fixed point). The growth exponent is the
least-squares slope of log time against log N over N = 16..1024 (``--quick``: over all points). Per N also the
interconnection's error bound ``eps``, the ``w`` cells its final node admits on average (of 33) and the sample
counts used (they grow with N). If an N fails (error, timeout, memory) the next ones are not run, and the gap
between the last N that worked and the first that failed is bisected (``--bisect`` probes).

The same N then run with ``interconnection.error: max`` (``declared_max``: the map declared the maximum of the
states, abstracted exactly by a reduction tree; eps 0 and at most 3 admitted w cells at every N).
"""

from __future__ import annotations

import math
from typing import Any

from bench.harness import EXAMPLES, Emit, Put, StageClock, case_record, fmt, limits, progress, run_child, slope

#: The paper's Fig. 3 gives no numbers to divide by.
PAPER = {
    "seconds_by_N": None,
    "source": "Sec. 5.1, Fig. 3 (runtime bars for N up to 32): the figure's data are not in the paper's source "
              "(its \\includegraphics is empty) and the text gives no numbers, so there is nothing to divide by",
}
#: Issue 24's targets (issue 6 had N = 128).
TARGETS = {"scalability_N": 1024, "scalability_exponent": 1.3}  # the exponent over 16..1024


# ====================================================================================== child side
def child_scalability(p: dict, emit: Emit) -> None:
    """One N of the scalability example: abstraction stages (no audit) and the composition."""
    from pipelines.spec.model import load_spec
    from pipelines.synthesis.cpre import ControllablePredecessor
    from workers.job import run_abstraction

    spec = load_spec(EXAMPLES / "scalability.yaml", {"N": p["N"]})
    if p.get("error") and spec.interconnection is not None and p["error"] != spec.interconnection.error:
        # error: max declares w = max(x) (pipelines/interconnection/reduction.py): the exact tree, eps 0
        spec = spec.model_copy(update={"interconnection": spec.interconnection.model_copy(update={"error": p["error"]})})
    clock = StageClock(emit)
    r = run_abstraction(spec, progress=clock, audit=False)
    ia = r.interconnection
    final = [n for n in ia.nodes if n.output.startswith("w")]
    res = (ia.details.get("certify_resolution") or {}).get("w0", {})
    emit({"type": "info", "stage_seconds": r.report["stage_seconds"], "abstract_states": r.report["abstract_states"],
          "interconnection": {  # how informative M̂ is: a w cell range of 33 cells allows every w
              "error_bound": float(ia.error_bounds[0]), "nodes": len(ia.nodes),
              "certify_cells_per_axis": (res.get("cells_per_axis") or [None])[0],
              "final_node_mean_w_cells": final[0].mean_cells() if final else None,
              "w_cells": int(r.network.internal_grids[0].size),
              "whole_box": 0 in ia.details.get("whole_box_outputs", ()),
              "samples_used": ia.details.get("samples_used"),
              "support_added_by_joint_check": len((ia.details.get("support_added_by_joint_check") or [[]])[0])}})
    clock.mark("other")
    game = ControllablePredecessor.from_network(r.network, r.relations, r.interconnection)
    clock.mark("composition")
    bs = game.model.build_seconds
    emit({"type": "info", "composition": {
        "relations_seconds": sum(v for k, v in bs.items() if k.startswith("T")),
        "interconnection_seconds": bs.get("interconnection"),
        "cpre_setup_seconds": game.setup_seconds,
        "live_nodes": len(game.model.bdd),
        "variables": len(game.model.variables),
        "interconnection_nodes": sum(part.dag_size for part in game.parts.values()),
    }})


CHILDREN = {"scalability": child_scalability}


# ====================================================================================== parent side
def run(args: Any) -> dict:
    """The paper's series (``certify``, the example as written) with its targets, then the same N declared
    ``error: max`` (exact reduction tree, eps 0) under ``declared_max``."""
    rec = series(args, "certify")
    rec["declared_max"] = series(args, "max")
    return rec


def series(args: Any, error: str) -> dict:
    """Every N in turn (and the bisection of a failure), the fitted exponents; prints a line per N (stdout)."""
    Ns = [4, 8, 16] if args.quick else [4 * 2 ** k for k in range(9)]  # 4 ... 1024
    fit_from = 4 if args.quick else 16
    points: list[dict] = []
    failed = None
    tag = "" if error == "certify" else f" error={error}"
    for N in Ns:
        pt = case_record(f"scalability N={N}{tag}", run_child("scalability", {"N": N, "error": error}, *limits(args)),
                         N=N)
        points.append(pt)
        progress(pt)
        if pt["status"] != "ok":
            failed = N
            break
    probes = []
    ok_Ns = [p["N"] for p in points if p["status"] == "ok"]
    breaks: dict[str, Any] | None
    if failed is not None and ok_Ns and args.bisect > 0:
        lo, hi = max(ok_Ns), failed
        for _ in range(args.bisect):
            if hi - lo <= 1:
                break
            mid = (lo + hi) // 2
            pt = case_record(f"scalability N={mid}{tag} (probe)",
                             run_child("scalability", {"N": mid, "error": error}, *limits(args)), N=mid)
            probes.append(pt)
            progress(pt)
            if pt["status"] == "ok":
                lo = mid
            else:
                hi = mid
        breaks = {"largest_ok": lo, "smallest_failed": hi}
    else:
        breaks = None if failed is None else {"largest_ok": max(ok_Ns) if ok_Ns else None, "smallest_failed": failed}

    fit_pts = [p for p in points if p["status"] == "ok" and p["N"] >= fit_from]
    exponents = {}
    for key in ("abstraction", "composition", "total"):
        xs = [math.log(p["N"]) for p in fit_pts]
        ys = [math.log(max(1e-9, _series(p)[key])) for p in fit_pts]
        exponents[key] = slope(xs, ys) if len(xs) >= 2 else None
    failure = next(({"N": p["N"], "status": p["status"], "error": p["error"], "traceback": p.get("traceback")}
                    for p in points + probes if p["status"] != "ok"), None)
    for p in points + probes:
        p["series"] = _series(p)
    print("\n".join(point_lines(points + probes, exponents, [p["N"] for p in fit_pts], error)))
    return {
        "case": "scalability",
        "status": "ok" if failed is None else "partial",
        "error": None if failure is None else f"N={failure['N']}: {failure['error']}",
        "points": points,
        "probes": probes,
        "exponents": exponents,
        "fit_range": [fit_pts[0]["N"], fit_pts[-1]["N"]] if fit_pts else None,
        "fit_N": [p["N"] for p in fit_pts],
        "breaks": breaks,
        "failure": failure,
        "paper": PAPER,
        "vs_paper": {},
    }


def _series(p: dict) -> dict[str, float]:
    st = p["stages"]
    abst = sum(st[k]["wall"] for k in ("plan", "lipschitz", "subsystems", "interconnection") if k in st)
    comp = st.get("composition", {}).get("wall", 0.0)
    return {"abstraction": abst, "composition": comp, "total": abst + comp}


# ====================================================================================== table and targets
def point_lines(rows: list[dict], exponents: dict, fit_N: list[int], error: str = "certify") -> list[str]:
    """Per N: seconds, the interconnection's error bound and admitted w cells, the sample counts."""
    out = [f"scalability (interconnection.error: {error}) per N: seconds (abstraction + composition), interconnection "
           "error bound eps, w cells its final node admits on average (of 33), training / joint-check samples, "
           "coordinates the joint check added"]
    for p in rows:
        ic = (p.get("details") or {}).get("interconnection") or {}
        used = ic.get("samples_used") or {}
        s = p.get("series") or {}
        out.append(f"  N={p['N']:<5} {p['status']:<8} {fmt(s.get('total')):>8} s ({fmt(s.get('abstraction'))} + "
                   f"{fmt(s.get('composition'))})  eps {fmt(ic.get('error_bound'))}  w cells "
                   f"{fmt(ic.get('final_node_mean_w_cells'))}{' (whole box)' if ic.get('whole_box') else ''}  samples "
                   f"{used.get('training')} / {used.get('joint_check')}  added {ic.get('support_added_by_joint_check')}")
    out.append(f"  growth exponent over N={fit_N}: " + ", ".join(f"{k} {fmt(v)}" for k, v in exponents.items())
               + " (target <= 1.3 for the total)")
    return out


def lines(s: dict) -> list[str]:
    """The case's lines among the baselines: the exponents, and each series' N, eps, admitted w cells, seconds."""
    ex = s["exponents"]
    out = [f"  scalability exponent over N={s['fit_N']}: abstraction {fmt(ex['abstraction'])}, composition "
           f"{fmt(ex['composition'])}, total {fmt(ex['total'])}" + (f"; breaks: {s['breaks']}" if s["breaks"] else "")]
    for label, rec in (("paper's certify", s), ("declared max", s.get("declared_max"))):
        if not rec:
            continue
        out.append(f"  scalability, {label}: N, eps, w cells admitted (of 33), seconds")
        for p in rec["points"]:
            ic = (p.get("details") or {}).get("interconnection") or {}
            out.append(f"    N={p['N']:<5} {p['status']:<8} eps {fmt(ic.get('error_bound'))}  w cells "
                       f"{fmt(ic.get('final_node_mean_w_cells'))}  {fmt((p.get('series') or {}).get('total'))} s")
    dm = s.get("declared_max")
    if dm:
        out.append(f"  scalability, declared max: exponent over N={dm['fit_N']}: total {fmt(dm['exponents']['total'])}")
    return out


def targets(s: dict, put: Put) -> None:
    """The largest N reached and the growth exponent over 16..1024."""
    reached = max((p["N"] for p in s["points"] if p["status"] == "ok"), default=None)
    put("scalability largest N", reached, f">= {TARGETS['scalability_N']}", (reached or 0) >= TARGETS["scalability_N"])
    e = s["exponents"]["total"]
    full = s["fit_N"] and s["fit_N"][-1] >= TARGETS["scalability_N"]
    put(f"scalability exponent N={s['fit_range']}", e,
        f"<= {TARGETS['scalability_exponent']} (16..{TARGETS['scalability_N']})",
        bool(full) and e is not None and e <= TARGETS["scalability_exponent"])
