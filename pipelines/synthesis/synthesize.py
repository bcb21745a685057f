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
from pipelines.symbolic.relations import region
from pipelines.symbolic.symbolic_model import Function, SymbolicModel
from pipelines.synthesis import contracts
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
from pipelines.synthesis.options import SynthesisOptions
from pipelines.synthesis.product import letter_sets, reach_symbolic
from pipelines.synthesis.quotient import Refinement, quotient
from pipelines.temporal.labels import Labelling

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.abstraction.relation import SubsystemRelation
    from pipelines.grid import UniformGrid
    from pipelines.interconnection import InterconnectionAbstraction
    from pipelines.network import Network
    from pipelines.spec.model import SpecificationSpec

def synthesize(
    network: Network,
    relations: Mapping[str, SubsystemRelation],
    interconnection: InterconnectionAbstraction,
    specification: SpecificationSpec,
    options: SynthesisOptions | None = None,
    *,
    partitioned: PartitionedFactory | None = None,
    progress: IterationProgress | None = None,
    checkpoints: Checkpoints | None = None,
) -> tuple[ControllablePredecessor, dict[str, Any], dict[str, Any]]:
    """Encode an abstraction, solve its specification, and report.

    Parameters
    ----------
    network, relations, interconnection
        The abstraction: the network, the subsystem relations by key, the interconnection abstraction.
    specification : SpecificationSpec
        The job spec's ``specification`` section (kind and regions).
    options : SynthesisOptions, optional
        What is computed and how (:class:`~.options.SynthesisOptions`, e.g. ``SynthesisOptions.from_spec``;
        ``None``: the defaults); an ``ltl`` specification's automaton, whose product game is solved
        (:func:`~.product.reach_symbolic`; the result under ``ltl``).
    partitioned : callable, optional
        ``partitioned(cpre, processes)``: the partitioned ``∃u.CPre`` (e.g.
        ``workers.processes.partitioned_cpre.PartitionedPredecessors``, or ``workers.dask_cpre.on_cluster(client)``
        for the job's Dask workers); ``None``: one process. Its parts stop before this returns.
    progress : callable, optional
        ``progress(iteration, message)``, once per iteration of every fixed point, inner ones included
        (:data:`~.fixed_points.IterationProgress`); the BDDs are built before the first call.
    checkpoints : Checkpoints, optional
        Where the safety fixed points store their iterates and resume from (:mod:`~.checkpoints`).

    Returns
    -------
    cpre : ControllablePredecessor
        The model and the CPre ingredients the controllers are made of (:func:`pipelines.controller.controller_of`):
        the fine game's, also with a quotient (its ``CPre`` holds the quotient's, see :mod:`~.quotient`).
    results : dict of str to SynthesisResult
        One entry (``safe``, ``reach``, ``reach_avoid``; ``ltl``: a :class:`~.product.SymbolicProductResult`) or one
        per reach-and-stay method.
    report : dict
        JSON-ready: build times and node counts, per-result summaries; ``domain_bound`` names the initial states
        (``options.initial_cells``) :mod:`~.domain_bound` proves outside the domain (also a progress line, long
        before a large fixed point ends).
    """
    o = options if options is not None else SynthesisOptions()
    t0 = time.perf_counter()
    local_only = (specification.kind == "safe" and "contracts" in o.reach_and_stay_methods) or (
        specification.kind == "reach_and_stay" and set(o.reach_and_stay_methods) == {"contracts"})
    method = "local" if local_only and o.method == "auto" else o.method
    cpre = ControllablePredecessor.from_network(network, relations, interconnection, order=o.order,
                                                method=method, max_memory=o.max_memory, chain_order=o.chain_order,
                                                processes=o.processes, partitioned=partitioned,
                                                auto_parts=o.auto_parts, parallel_after=o.parallel_after,
                                                symmetry=o.symmetry,
                                                say=None if progress is None else (lambda message: progress(0, message)))
    build = time.perf_counter() - t0
    t0 = time.perf_counter()
    try:
        game = quotient(cpre, o.quotient_level)
    except BaseException:
        cpre.close()
        raise
    quotient_seconds = time.perf_counter() - t0
    sets = _SpecificationSets(cpre.model, specification, network.composed_state_grid())
    kind = specification.kind
    try:
        if kind == "ltl":  # the product game: no target, safe or avoid set to bound the domain with
            if o.automaton is None:
                raise ValueError("an 'ltl' specification is solved with its automaton (SynthesisOptions.automaton)")
            labelling = Labelling.of(o.automaton.atoms, specification.regions or {}, network.composed_state_grid())
            product = reach_symbolic(game, o.automaton, letter_sets(cpre.model, labelling), progress)
            return cpre, {"ltl": product}, _report(cpre, game, {"ltl": product}, None, build, quotient_seconds, 0)
        S = sets.get("safe") if kind != "safe" and specification.safe is not None else None
        bound_report = None if cpre.method == "local" else _domain_bound(
            cpre, kind, sets.get("safe" if kind == "safe" else "target"), S,
            sets.get("avoid") if kind == "reach_avoid" else None, o.initial_cells, progress)
        results = _solve(cpre, game, kind, sets, S, o, progress, checkpoints)
    finally:
        if game is not cpre:
            game.close()
        cpre.close()
    return cpre, results, _report(cpre, game, results, bound_report, build, quotient_seconds, o.refine_rounds)


class _SpecificationSets:
    """The specification's regions as BDDs over the composed state bits, each built once (the domain bound and
    the fixed points both read them). Targets and safe sets from inside, avoid sets from outside (docs/method.md
    §1): an abstract winning run then satisfies the concrete specification."""

    def __init__(self, model: SymbolicModel, specification: SpecificationSpec, grid: UniformGrid) -> None:
        self.model, self.specification, self.grid = model, specification, grid
        self.built: dict[str, Function] = {}

    def get(self, name: str) -> Function:
        """The region ``name`` (``target``, ``safe`` or ``avoid``) of the specification."""
        if name not in self.built:
            self.built[name] = region(self.model, abstract_region(getattr(self.specification, name), self.grid,
                                                                  f"specification.{name}", outer=(name == "avoid")))
        return self.built[name]


def _solve(cpre: ControllablePredecessor, game: ControllablePredecessor, kind: str, sets: _SpecificationSets,
           S: Function | None, o: SynthesisOptions, progress: IterationProgress | None,
           checkpoints: Checkpoints | None) -> dict[str, SynthesisResult]:
    """The fixed point of the specification's kind on ``game`` (the fine game ``cpre`` or its quotient, refined
    by ``o.refine_rounds`` rounds where it is one), within the safe set ``S`` (``None``: none besides a ``safe``
    specification's own); the results by name as :func:`synthesize` returns them."""
    refine = Refinement(cpre, o.refine_rounds) if o.refine_rounds and game is not cpre else None
    layered = o.controller_form == "layered" or (o.controller_form == "auto" and cpre.method in ("shared", "chained"))
    if kind == "safe" and "contracts" in o.reach_and_stay_methods:
        return {"contracts": contracts.solve(cpre, None, sets.get("safe"), progress)}
    if kind == "safe":
        return {"safe": safe(game, sets.get("safe"), layered=layered, progress=progress,
                             local_games=o.local_games, checkpoints=checkpoints, refine=refine)}
    if kind == "reach":
        return {"reach": reach(game, sets.get("target"), layered=layered, safe=S, progress=progress)}
    if kind == "reach_avoid":
        return {"reach_avoid": reach_avoid(game, sets.get("target"), sets.get("avoid"), layered=layered, safe=S,
                                           progress=progress)}
    exact = tuple(m for m in o.reach_and_stay_methods if m != "contracts")
    results = reach_and_stay(game, sets.get("target"), exact, layered=layered, safe=S, progress=progress,
                             local_games=o.local_games, checkpoints=checkpoints, refine=refine) if exact else {}
    if "contracts" in o.reach_and_stay_methods:
        results["contracts"] = contracts.solve(cpre, sets.get("target"), S, progress)
    return results


def _report(cpre: ControllablePredecessor, game: ControllablePredecessor, results: Mapping[str, Any],
            bound_report: dict[str, Any] | None, build: float, quotient_seconds: float, refine_rounds: int
            ) -> dict[str, Any]:
    """:func:`synthesize`'s report (JSON-ready): the encoding ``cpre`` (its build took ``build`` seconds), the
    game solved and its results, the domain bound's report, and a ``quotient`` entry where the game is one."""
    m = cpre.model
    report: dict[str, Any] = {
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
    return report


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
