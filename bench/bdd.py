"""The ``bdd`` case (d): a subsystem relation built as one BDD in bulk against one cube per constraint.

One subsystem relation built as a BDD from its interval arrays (the bulk Shannon tree of
:func:`pipelines.symbolic.tree.range_leaves` and :func:`~pipelines.symbolic.tree.tree`) against a naive
construction, the OR of one cube per (cell, input, internal cell) constraint conjoined with its successor interval;
both must give the same BDD. Ratio = naive CPU / bulk CPU, the smallest over the specs.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

from bench.harness import (
    EXAMPLES,
    Emit,
    Put,
    baseline,
    baseline_lines,
    case_record,
    fmt,
    given_constants,
    limits,
    run_child,
)


def child_bdd(p: dict, emit: Emit) -> None:
    """(d) Bulk Shannon-tree construction of a relation against OR-ing one cube per constraint."""
    import numpy as np

    from pipelines.abstraction.cells import abstract_cells
    from pipelines.abstraction.relation import assemble, chunk_ranges
    from pipelines.network import build_network
    from pipelines.spec.model import load_spec
    from pipelines.symbolic.relations import subsystem_relation
    from pipelines.symbolic.symbolic_model import SymbolicModel
    from pipelines.symbolic.tree import range_leaves, tree

    spec = load_spec(p["spec"], p.get("set"))
    network = build_network(spec, None)
    sub = network.subsystems[p.get("subsystem", 0)]
    L_x, L_w = given_constants(sub)
    parts = [abstract_cells(sub, a, b, L_x, L_w, sub.spec.growth_bound, sub.spec.scp_objective)
             for a, b in chunk_ranges(sub, None)]
    rel = assemble(parts, sub.state_grid.size, sub.spec.growth_bound, L_x, L_w)
    readers: dict[int, int] = {}
    for s in network.subsystems:
        for j in s.reads:
            readers[j] = readers.get(j, 0) + 1
    order = "interleaved" if all(c <= 1 for c in readers.values()) else "shared_top"

    k = min(sub.state_grid.size, p.get("state_cells") or sub.state_grid.size)
    lo, hi, blocking = rel.lo[:k], rel.hi[:k], rel.blocking[:k]
    _, n_u, n_w = blocking.shape
    N = k * n_u * n_w
    state_shape = tuple(sub.state_grid.shape)
    w_shape = tuple(network.internal_grids[j].size for j in sub.reads) or (1,)
    xi, ui, wi = np.unravel_index(np.arange(N, dtype=np.int64), (k, n_u, n_w))
    cols = list(np.unravel_index(xi, state_shape)) + [ui]
    if sub.reads:
        cols += list(np.unravel_index(wi, w_shape))
    values = np.stack(cols, axis=1)
    lo2, hi2, blk = lo.reshape(N, -1), hi.reshape(N, -1), blocking.reshape(N)

    def fresh():
        m = SymbolicModel.from_network(network, None, order=order)
        return m, m.subsystem_digits(m.subsystems[sub.index])

    def bulk(m, dg):
        ids, leaves = range_leaves(m, dg["xn"], lo2, hi2, blk)
        return tree(m, dg["x"] + dg["u"] + dg["w"], values, ids, leaves)

    def naive(m, dg):
        digits = dg["x"] + dg["u"] + dg["w"]
        f = m.bdd.false
        for r in np.flatnonzero(~blk):
            assign = {}
            for d, digit in enumerate(digits):
                bits = m.bits[digit]
                v = int(values[r, d])
                for q, name in enumerate(bits):
                    assign[name] = bool((v >> (len(bits) - 1 - q)) & 1)
            g = m.bdd.cube(assign)
            for d, digit in enumerate(dg["xn"]):
                g &= m.interval(digit, int(lo2[r, d]), int(hi2[r, d]))
            f |= g
        return f

    times = {}
    for name, fn in (("bulk", bulk), ("naive", naive)):
        best = math.inf
        for _ in range(p.get("repeat", 1) if name == "naive" else max(3, p.get("repeat", 1))):
            m, dg = fresh()  # a fresh manager each time: no nodes left from an earlier build
            c0 = time.process_time()
            f = fn(m, dg)
            best = min(best, time.process_time() - c0)
        times[name] = best
        if name == "naive":
            same = bool(f == bulk(m, dg))
            nodes = f.dag_size
    m, _ = fresh()
    c0 = time.process_time()
    subsystem_relation(m, m.subsystems[sub.index], rel)
    full = time.process_time() - c0
    constraints = int((~blk).sum())
    emit({"type": "row", "row": {
        "spec": Path(p["spec"]).name, "subsystem": sub.name, "order": order, "state_cells": k,
        "triples": N, "constraints": constraints, "bulk_cpu": times["bulk"], "naive_cpu": times["naive"],
        "speedup": times["naive"] / times["bulk"], "same_bdd": same, "nodes": nodes,
        "bulk_us_per_constraint": 1e6 * times["bulk"] / max(1, constraints),
        "naive_us_per_constraint": 1e6 * times["naive"] / max(1, constraints),
        "full_relation_cpu": full, "full_relation_triples": int(rel.blocking.size),
    }})


CHILDREN = {"bdd": child_bdd}


def run(args: Any) -> dict:
    """Each spec's relation in a child; the smallest speed-up, and whether every pair of BDDs was the same."""
    if args.quick:
        specs: list[tuple[Path, dict]] = [(EXAMPLES / "small.yaml", {"state_cells": 12})]
    else:
        specs = [(EXAMPLES / "tanks.yaml", {"subsystem": 1}), (EXAMPLES / "consensus.yaml", {})]
    rows, children = [], []
    for spec, extra in specs:
        child = run_child("bdd", {"spec": str(spec), **extra}, *limits(args))
        children.append(case_record(f"bdd {spec.stem}", child, spec=spec.name))
        rows += [e["row"] for e in child["events"] if e["type"] == "row"]
    return baseline("bdd", children, rows=rows, ratio=min((r["speedup"] for r in rows), default=None),
                    ratio_meaning="naive (OR of cubes) CPU / bulk Shannon tree CPU, smallest",
                    all_same_bdd=all(r["same_bdd"] for r in rows) if rows else None)


def lines(c: dict) -> list[str]:
    return baseline_lines("bdd", c, [
        f"    {r['spec']}:{r['subsystem']} ({r['order']}), {r['constraints']} constraints: bulk "
        f"{r['bulk_us_per_constraint']:.1f} us, naive {r['naive_us_per_constraint']:.1f} us per constraint "
        f"-> {r['speedup']:.1f}x, same BDD: {fmt(r['same_bdd'])}"
        for r in c["rows"]])


def targets(c: dict, put: Put) -> None:
    v = c["ratio"]
    put("bulk BDD speed-up (least)", v, "> 1", v is not None and v > 1)
