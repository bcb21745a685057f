"""A job's synthesis: encode the abstraction, solve its specification, report (Algorithm 5; docs/method.md §5-6).

:func:`synthesize` takes the three parts of an abstraction (the network, the subsystem relations, the
interconnection abstraction) and the specification section of the job spec; it knows nothing of how the
abstraction was computed or where it is stored. Helper processes for the fixed points' ``∃u.CPre`` come in
through ``partitioned`` (:class:`~.cpre.ControllablePredecessor`), never from here.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from pipelines.spec.regions import AbstractRegion, abstract_region
from pipelines.symbolic.counting import count_states
from pipelines.symbolic.model import Function
from pipelines.symbolic.relations import region
from pipelines.synthesis.checkpoints import Checkpoints
from pipelines.synthesis.cpre import ControllablePredecessor, PartitionedFactory
from pipelines.synthesis.domain_bound import domain_bound
from pipelines.synthesis.fixed_points import (
    IterationProgress,
    SynthesisResult,
    reach,
    reach_and_stay,
    reach_avoid,
    safe,
)
from pipelines.synthesis.quotient import Refinement, quotient

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.abstraction.relation import SubsystemRelation
    from pipelines.interconnection import InterconnectionAbstraction
    from pipelines.network import Network
    from pipelines.spec.model import SpecificationSpec

CONTROLLER_FORMS = ("auto", "explicit", "layered")


def synthesize(
    network: Network,
    relations: Mapping[str, SubsystemRelation],
    interconnection: InterconnectionAbstraction,
    specification: SpecificationSpec,
    *,
    order: str | None = None,
    method: str = "auto",
    max_memory: int | None = None,
    reach_and_stay_methods: Sequence[str] = ("cobuchi", "reach_safe"),
    chain_order: str = "greedy",
    controller_form: str = "auto",
    processes: int | str = 1,
    partitioned: PartitionedFactory | None = None,
    auto_parts: int | None = None,
    parallel_after: float = 1.0,
    progress: IterationProgress | None = None,
    symmetry: bool = True,
    local_games: bool = True,
    checkpoints: Checkpoints | None = None,
    initial_cells: Sequence[tuple[Sequence[int], Sequence[int]]] = (),
    quotient_level: int = 0,
    refine_rounds: int = 0,
) -> tuple[ControllablePredecessor, dict[str, SynthesisResult], dict[str, Any]]:
    """Encode an abstraction, solve its specification, and report.

    Parameters
    ----------
    network, relations, interconnection
        The abstraction: the network, the subsystem relations by key, the interconnection abstraction.
    specification : SpecificationSpec
        The job spec's ``specification`` section (kind and regions).
    order, method, max_memory, chain_order
        See :meth:`ControllablePredecessor.from_network`.
    reach_and_stay_methods : sequence of str
        Fixed points for a reach-and-stay specification (:func:`~.fixed_points.reach_and_stay`).
    controller_form : {'auto', 'explicit', 'layered'}
        ``explicit`` (a BDD over states and inputs), ``layered`` (:class:`SynthesisResult` ``layers``) or
        ``auto``, which is ``layered`` for the shared-``w`` CPre: there the explicit controller is the largest BDD
        of the job (consensus N = 8: 2.4 GB as DDDMP, most of the synthesis time).
    processes : int or 'auto'
        Parts of the fixed points' ``∃u.CPre`` run at once (:class:`ControllablePredecessor`); they take effect
        only with ``partitioned``, and stop before this returns.
    partitioned : callable, optional
        ``partitioned(cpre, processes)``: the partitioned ``∃u.CPre`` (e.g.
        ``workers.processes.partitioned_cpre.PartitionedPredecessors``, or ``workers.dask_cpre.on_cluster(client)``
        for the job's Dask workers); ``None``: one process.
    auto_parts, parallel_after
        What ``processes='auto'`` means when the parts run elsewhere, and how long one step must take in one
        process before the parts start (:class:`~.cpre.ControllablePredecessor`).
    progress : callable, optional
        ``progress(iteration, message)``, once per iteration of every fixed point, inner ones included
        (:data:`~.fixed_points.IterationProgress`); the BDDs are built before the first call.
    symmetry : bool
        Use interchangeable subsystems (:mod:`~.symmetry`; the same results, faster where there are some).
    local_games : bool
        Start safety fixed points from the bound of :mod:`~.local_games` (the same results, faster where
        subsystems read few others).
    checkpoints : Checkpoints, optional
        Where the safety fixed points store their iterates and resume from (:mod:`~.checkpoints`).
    initial_cells : sequence of (first, last) index vectors
        Per initial state of the spec, the box of cells that contain it (a point on a boundary is in several).
        :mod:`~.domain_bound` is computed before the fixed points, and
        ``report["domain_bound"]["initial_states_outside"]`` (and a progress line) names those
        it proves outside the domain, long before a large fixed point ends.
    quotient_level : int
        Solve the fixed points on the quotient that merges ``2^k`` neighbouring cells per state coordinate
        (:mod:`~.quotient`): sound controllers whose domains may be smaller than the maximal ones, for cases whose
        exact fixed points are too large. ``0``: the exact game. The domain bound is the fine game's either way.
    refine_rounds : int
        With a quotient: rounds of growing its safety invariant on the fine game (:class:`~.quotient.Refinement`;
        ``safe`` and Reach(Safe)); ``0``: none.

    Returns
    -------
    cpre : ControllablePredecessor
        The model and the CPre ingredients the controllers are made of (:func:`pipelines.controller.controller_of`):
        the fine game's, also with a quotient (its ``CPre`` holds the quotient's, see :mod:`~.quotient`).
    results : dict of str to SynthesisResult
        One entry (``safe``, ``reach``, ``reach_avoid``) or one per reach-and-stay method.
    report : dict
        JSON-ready: build times and node counts, per-result summaries.
    """
    if controller_form not in CONTROLLER_FORMS:
        raise ValueError(f"controller_form must be auto, explicit or layered, got {controller_form!r}")
    if refine_rounds and not quotient_level:
        raise ValueError("refine_rounds grows a quotient's invariant: it needs quotient_level > 0")
    t0 = time.perf_counter()
    cpre = ControllablePredecessor.from_network(network, relations, interconnection, order=order, method=method,
                                                max_memory=max_memory, chain_order=chain_order, processes=processes,
                                                partitioned=partitioned, auto_parts=auto_parts,
                                                parallel_after=parallel_after, symmetry=symmetry)
    build = time.perf_counter() - t0
    m = cpre.model
    t0 = time.perf_counter()
    try:
        game = quotient(cpre, quotient_level)
    except BaseException:
        cpre.close()
        raise
    quotient_seconds = time.perf_counter() - t0
    refine = Refinement(cpre, refine_rounds) if refine_rounds and game is not cpre else None
    grid = network.composed_state_grid()

    built: dict[str, Function] = {}

    def states(name: str) -> Function:
        # Targets and safe sets from inside, avoid sets from outside (docs/method.md §1): an abstract winning run then
        # satisfies the concrete specification. Built once: the domain bound and the fixed points both read them.
        if name not in built:
            built[name] = region(m, abstract_region(getattr(specification, name), grid, f"specification.{name}",
                                                    outer=(name == "avoid")))
        return built[name]

    layered = controller_form == "layered" or (controller_form == "auto" and cpre.method == "shared")
    kind = specification.kind
    bound_report: dict[str, Any] | None = None
    try:
        S = states("safe") if kind != "safe" and specification.safe is not None else None
        bound_report = _domain_bound(cpre, kind, states("safe" if kind == "safe" else "target"), S,
                                     states("avoid") if kind == "reach_avoid" else None, initial_cells, progress)
        if kind == "safe":
            results = {"safe": safe(game, states("safe"), layered=layered, progress=progress,
                                    local_games=local_games, checkpoints=checkpoints, refine=refine)}
        elif kind == "reach":
            results = {"reach": reach(game, states("target"), layered=layered, safe=S, progress=progress)}
        elif kind == "reach_avoid":
            results = {"reach_avoid": reach_avoid(game, states("target"), states("avoid"), layered=layered, safe=S,
                                                  progress=progress)}
        else:
            results = reach_and_stay(game, states("target"), reach_and_stay_methods, layered=layered, safe=S,
                                     progress=progress, local_games=local_games, checkpoints=checkpoints,
                                     refine=refine)
    finally:
        if game is not cpre:
            game.close()
        cpre.close()
    report = {
        "order": m.order,
        "method": cpre.method,
        "chain_order": cpre.chain_order,
        "build_seconds": build,
        "relation_seconds": dict(m.build_seconds),
        "cpre_setup_seconds": cpre.setup_seconds,
        "relation_nodes": [t.dag_size for t in cpre.T],
        "interconnection_nodes": {f"w{j}": p.dag_size for j, p in cpre.parts.items()},
        "results": {k: r.summary() for k, r in results.items()},
        "parallel": game.parallel,
        "symmetry": None if game.symmetry is None else game.symmetry.describe(),
        "bdd": m.stats(),
    }
    if bound_report is not None:
        report["domain_bound"] = bound_report
    if game is not cpre:
        report["quotient"] = {"level": game.level, "cells_per_block": 2 ** game.level,
                              "seconds": quotient_seconds, "relation_nodes": [t.dag_size for t in game.T],
                              "refine_rounds": refine_rounds, "maximal": False}
    return cpre, results, report


def _domain_bound(
    cpre: ControllablePredecessor, kind: str, region_set: Function, safe_set: Function | None,
    avoid: Function | None, initial_cells: Sequence[tuple[Sequence[int], Sequence[int]]],
    progress: IterationProgress | None,
) -> dict[str, Any] | None:
    """:func:`~.domain_bound.domain_bound` and the initial states it rules out (JSON-ready; ``None`` for a network
    without upstream-closed groups)."""
    bound = domain_bound(cpre, kind, region_set, safe=safe_set, avoid=avoid)
    if not bound.groups:
        return None
    m = cpre.model
    names = [s.name for s in m.subsystems]
    outside = []
    for k, (first, last) in enumerate(initial_cells):
        cells = region(m, AbstractRegion(((np.asarray(first), np.asarray(last)),)))
        if cells == m.bdd.false:
            continue  # off the grid: the closed loop's own warning says so
        members = bound.ruled_out_by(cells)
        if members is not None:
            group = [names[i] for i in members]
            outside.append({"index": k, "group": group})
            if progress is not None:
                progress(0, f"domain bound: initial state {k} is outside the domain (the game of "
                            f"{', '.join(group)} alone cannot win from it)")
    return {**bound.summary(), "groups": [[names[i] for i in g] for g in bound.groups],
            "domain_states_at_most": count_states(m, bound.bound & m.x_domain), "initial_states_outside": outside}
