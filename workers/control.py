"""The control stages of a job: synthesis, the controller's files, the closed loop and the figures.

Called by the orchestrator (:func:`workers.job.run_job`) after the abstraction stages. Synthesis runs in this
process (one CUDD manager per process); once one step of a fixed point takes ``options.synthesis_parallel_after``
seconds, the partitioned ``∃u.CPre`` runs on the job's Dask workers (:mod:`workers.dask_cpre`) when the job has a
cluster, else in helper processes (:mod:`workers.processes.partitioned_cpre`) when
``options.synthesis_processes`` allows more than one (:func:`partitioning`).
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from pipelines.array_controller import ArrayController
from pipelines.controller import controller_of
from pipelines.errors import SpecError
from pipelines.product_controller import ProductController
from pipelines.spec.regions import closed_loop_regions, spec_regions
from pipelines.synthesis import explicit
from pipelines.synthesis.engine_cpre import OnOxidd, resolve_engine
from pipelines.synthesis.explicit import ExplicitGame, ExplicitResult, choose_backend
from pipelines.synthesis.fixed_points import IterationProgress, SynthesisResult
from pipelines.synthesis.options import SynthesisOptions
from pipelines.synthesis.product import ProductResult, reach_explicit
from pipelines.synthesis.synthesize import synthesize
from pipelines.temporal.automaton import Automaton
from pipelines.temporal.labels import Labelling
from pipelines.verification.closed_loop import run_closed_loop
from pipelines.verification.empty_domain import explain_empty_domain
from pipelines.verification.product_loop import run_product_loop
from workers import checkpoint_store, jobdir
from workers.automata import spec_automaton
from workers.checkpoint_store import DirectoryCheckpoints, problem_key
from workers.dask_cpre import on_cluster, parts_for
from workers.figures import draw_figures
from workers.processes.partitioned_cpre import PartitionedPredecessors
from workers.stages import Abstraction, Progress, no_progress


def run_synthesis(
    abstraction: Abstraction,
    out_dir: str | os.PathLike[str] | None = None,
    *,
    progress: Progress = no_progress,
    runs: int | None = None,
    client: Any = None,
) -> dict[str, Any]:
    """Synthesize, save the controller, run the closed loop and draw the figures (docs/method.md §5-6).

    Parameters
    ----------
    abstraction : Abstraction
    out_dir : path, optional
        The job directory to write the controller files, figures and example run into (none if ``None``).
    runs : int, optional
        Closed-loop runs from random domain states (default: ``options.closed_loop_runs``).
    client : distributed.Client, optional
        The job's Dask client, open for the whole call: the fixed points' parts run on its workers
        (:func:`partitioning`).

    Returns
    -------
    dict
        The report entries ``domain_states``, ``domain_states_by_fixed_point``, ``controller``, ``synthesis``,
        ``closed_loop``, ``figures``, ``stage_seconds`` and ``warnings`` (:func:`synthesis_warnings`).

    Progress: ``("synthesis", 0, 1)`` while the BDDs are built, then ``("synthesis", k, k + 1)`` at the ``k``-th
    iteration of any fixed point (their number is unknown beforehand) and ``("synthesis", 1, 1)`` at the end.
    """
    spec, network = abstraction.spec, abstraction.network
    opts = spec.options
    if out_dir is not None:  # CUDD's DDDMP writer aborts the process on a missing directory
        os.makedirs(out_dir, exist_ok=True)
    kind = spec.specification.kind
    t0 = time.perf_counter()
    results, syn_report, make, store = _solve(abstraction, out_dir, progress, client)
    seconds = {"synthesis": time.perf_counter() - t0}
    main_key = opts.controller if kind == "reach_and_stay" else next(iter(results))
    main = results[main_key]
    controller, files = _save_controllers(abstraction, results, main_key, make, out_dir)
    if store is not None:
        store.clear()  # the controller files hold what the iterates were kept for

    t0 = time.perf_counter()
    loop = (_closed_loop(abstraction, controller, main, runs, progress) if kind != "ltl" else
            run_product_loop(network, controller, opts.initial_states, opts.closed_loop_runs if runs is None else runs,
                             opts.closed_loop_steps, np.random.default_rng(opts.seed + 1),
                             progress=lambda k, n: progress("closed_loop", k, n, "runs in lockstep")))
    seconds["closed_loop"] = time.perf_counter() - t0

    # The figures (workers.figures): drawn also for an empty domain, where the phase plane shows why.
    figures = [] if out_dir is None else draw_figures(network, controller, loop, out_dir)

    return {
        "domain_states": main.domain_states,
        "domain_states_by_fixed_point": {k: r.domain_states for k, r in results.items()},
        "controller": {"fixed_point": main_key,
                       "form": "product" if kind == "ltl" else
                       "layered" if isinstance(main, SynthesisResult) and main.layers else
                       "explicit" if isinstance(main, SynthesisResult) else "array",
                       "nodes": controller.nodes, "files": files},
        "synthesis": syn_report,
        "closed_loop": loop.summary(),
        "figures": figures,
        "stage_seconds": seconds,
        "warnings": synthesis_warnings(kind, main_key, {k: r.domain_states for k, r in results.items()},
                                       loop.initial_states, has_safe=spec.specification.safe is not None,
                                       quotient=opts.synthesis_quotient)
        + ([] if store is None else store.warnings)
        + _why_empty(abstraction, main_key, main),
    }


def _why_empty(abstraction: Abstraction, main_key: str, main: Any) -> list[str]:
    """Why the saved fixed point's domain is empty, if it is: the contracts' chain says where it stopped (box
    assumptions lose what the exact game may keep), the others are explained on the abstraction
    (:func:`~pipelines.verification.empty_domain.explain_empty_domain`)."""
    spec = abstraction.spec
    if main.domain_states or spec.specification.kind == "ltl":
        return []
    if main_key == "contracts":
        return [f"contracts: {main.details.get('outcome', 'lost')}. They assume each subsystem's neighbours "
                "anywhere in a box, never how fast they move; the exact fixed points (contracts left out of "
                "options.fixed_points) may win where they cannot (docs/method.md §6, Contracts)"]
    return explain_empty_domain(abstraction.network, abstraction.relations, abstraction.interconnection, spec)


def _solve(
    abstraction: Abstraction, out_dir: str | os.PathLike[str] | None, progress: Progress, client: Any,
) -> tuple[Mapping[str, SynthesisResult | ExplicitResult], dict[str, Any], Any, DirectoryCheckpoints | None]:
    """The ``synthesis`` stage's fixed points (Algorithm 5) on the back end the options choose
    (:func:`~pipelines.synthesis.explicit.choose_backend`): their results, the report, a maker of controllers and,
    for the BDD back end with a job directory, the checkpoints a stopped job resumes from."""
    spec = abstraction.spec
    opts = spec.options
    backend = choose_backend(opts.synthesis_backend if not opts.synthesis_quotient else "bdd", abstraction.network,
                             abstraction.relations)
    if opts.synthesis_quotient and opts.synthesis_backend == "explicit":
        raise SpecError("options.synthesis_quotient solves a quotient of the BDD game: set options.synthesis_backend "
                        "to 'bdd' or 'auto', or synthesis_quotient to 0")
    progress("synthesis", 0, 1, "building predecessor lists and solving" if backend == "explicit"
             else "building BDDs and solving")
    events = 0

    def iteration(_: int, message: str) -> None:
        nonlocal events
        events += 1
        progress("synthesis", events, events + 1, message)

    store: DirectoryCheckpoints | None = None
    results: Mapping[str, Any]
    automaton = None
    if spec.specification.kind == "ltl":  # MONA, under its time cap (workers.automata)
        t0 = time.perf_counter()
        automaton = spec_automaton(spec.specification, opts.max_automaton_states)
        progress("synthesis", 0, 1, f"automaton: {automaton.n_states} states over {len(automaton.atoms)} atoms in "
                 f"{time.perf_counter() - t0:.2f} s")
    if backend == "explicit":
        results, syn_report, make = _explicit_synthesis(abstraction, iteration, automaton)
    else:
        # A job stopped during a long safety fixed point resumes from its last iterate (no product game has one).
        if out_dir is not None and automaton is None:
            key = problem_key(spec.specification.model_dump(mode="json"), abstraction.relations,
                              abstraction.interconnection.nodes, quotient=opts.synthesis_quotient)
            store = DirectoryCheckpoints(Path(out_dir) / jobdir.CHECKPOINTS, key, every=checkpoint_store.EVERY)
        results, syn_report, make = _bdd_synthesis(abstraction, iteration, store, client, automaton)
    syn_report["backend"] = backend
    progress("synthesis", 1, 1, ", ".join(f"{k}: {r.domain_states}" for k, r in results.items()))
    return results, syn_report, make, store


def _save_controllers(
    abstraction: Abstraction, results: Mapping[str, SynthesisResult | ExplicitResult], main_key: str, make: Any,
    out_dir: str | os.PathLike[str] | None,
) -> tuple[Any, list[str]]:
    """The controller of the ``main_key`` fixed point and the names of its files in ``out_dir``; every other fixed
    point's controller is saved beside it (``controller_<key>``)."""
    spec, network = abstraction.spec, abstraction.network
    main = results[main_key]
    meta = {
        "kind": spec.specification.kind,
        "fixed_point": main_key,
        "state_grid": network.composed_state_grid().describe(),
        "input_grids": [s.input_grid.describe() for s in network.subsystems],
        "spec": spec.model_dump(mode="json"),
        "domain_states": main.domain_states,
    }
    controller = make(main, meta)
    files: list[str] = []
    if out_dir is not None:
        files = [p.name for p in controller.save(out_dir, jobdir.CONTROLLER)]
        for key, r in results.items():
            if key != main_key:
                make(r, {**meta, "fixed_point": key, "domain_states": r.domain_states}).save(
                    out_dir, f"{jobdir.CONTROLLER}_{key}"
                )
    return controller, files


def _closed_loop(
    abstraction: Abstraction, controller: Any, main: SynthesisResult | ExplicitResult, runs: int | None,
    progress: Progress,
) -> Any:
    """The ``closed_loop`` stage (Theorem 4.2): the concrete black boxes under the controller, from the spec's
    initial states in the domain and from random domain states, for twice the fixed point's iterations (plus a
    margin) unless the options give the steps."""
    spec, network = abstraction.spec, abstraction.network
    opts = spec.options
    rng = np.random.default_rng(opts.seed + 1)
    steps = opts.closed_loop_steps or (2 * (main.iterations + main.inner_iterations) + 30)
    checked = closed_loop_regions(spec, network, spec_regions(spec, network))
    return run_closed_loop(
        network, controller, opts.initial_states, opts.closed_loop_runs if runs is None else runs, steps, rng,
        spec.specification.kind, checked["target"], checked["avoid"], safe=checked["safe"],
        progress=lambda k, n: progress("closed_loop", k, n, "runs in lockstep"),
    )


def _bdd_synthesis(
    abstraction: Abstraction, progress: IterationProgress, store: DirectoryCheckpoints | None, client: Any,
    automaton: Automaton | None = None,
) -> tuple[dict[str, Any], dict[str, Any], Any]:
    """The BDD back end (:func:`pipelines.synthesis.synthesize.synthesize`, its parts where :func:`partitioning`
    says), its results, its report and a maker of the controllers (explicit or layered BDDs; with an ``ltl``
    specification's ``automaton``, the product game and a :class:`~pipelines.product_controller.ProductController`)."""
    spec, network = abstraction.spec, abstraction.network
    opts = spec.options
    initial = np.asarray(opts.initial_states or [], dtype=float).reshape(-1, network.state_dim)
    first, last = network.composed_state_grid().cells_touching(initial, initial)
    parts = partitioning(opts, client)
    options = replace(SynthesisOptions.from_spec(opts, list(zip(first.tolist(), last.tolist()))),
                      auto_parts=parts["auto_parts"], automaton=automaton)
    cpre, results, report = synthesize(network, abstraction.relations, abstraction.interconnection,
                                       spec.specification, options, partitioned=parts["partitioned"],
                                       progress=progress, checkpoints=store)
    if store is not None:
        report["checkpoints"] = store.describe()

    def make(result: Any, meta: dict[str, Any]) -> Any:
        if automaton is not None:
            labelling = Labelling.of(automaton.atoms, spec.specification.regions or {}, network.composed_state_grid())
            return ProductController.from_symbolic(cpre.model, result, labelling, meta)
        return controller_of(cpre, result, meta)

    return results, report, make


def _explicit_synthesis(
    abstraction: Abstraction, progress: IterationProgress, automaton: Automaton | None = None,
) -> tuple[dict[str, Any], dict[str, Any], Any]:
    """The explicit back end (:mod:`pipelines.synthesis.explicit`): the game on the relation's boxes, its fixed
    points (with an ``ltl`` specification's ``automaton``, the product game: :func:`_explicit_product`), and a maker
    of :class:`~pipelines.array_controller.ArrayController` objects; the report says what building the predecessor
    lists and each fixed point took."""
    spec, network = abstraction.spec, abstraction.network
    grid = network.composed_state_grid()
    (relation,) = abstraction.relations.values()
    game = ExplicitGame.from_relation(relation, grid.shape)
    progress(0, f"predecessor lists: {game.transitions:,} transitions in {game.build_seconds:.2f} s")
    if automaton is not None:
        return _explicit_product(abstraction, game, automaton, progress)
    t0 = time.perf_counter()
    results = explicit.solve(game, spec.specification, grid, tuple(spec.options.fixed_points), progress=progress)
    report = {
        "build_seconds": game.build_seconds,
        "fixed_point_seconds": time.perf_counter() - t0,
        "game": game.describe(),
        "results": {k: r.summary() for k, r in results.items()},
    }
    subsystem = network.subsystems[0].name

    def make(result: ExplicitResult, meta: dict[str, Any]) -> ArrayController:
        return ArrayController(result.admissible, result.layer, {**meta, "subsystem": subsystem})

    return results, report, make


def _explicit_product(abstraction: Abstraction, game: ExplicitGame, automaton: Automaton, progress: IterationProgress,
                      ) -> tuple[dict[str, ProductResult], dict[str, Any], Any]:
    """An ``ltl`` specification on the explicit back end: every cell's class of letters
    (:class:`~pipelines.temporal.labels.Labelling`), the product game (:func:`~pipelines.synthesis.product.reach_explicit`)
    and a maker of :class:`~pipelines.product_controller.ProductController` objects."""
    spec, network = abstraction.spec, abstraction.network
    grid = network.composed_state_grid()
    labelling = Labelling.of(automaton.atoms, spec.specification.regions or {}, grid)
    classes, cell_class = np.unique(labelling.classes(grid.unravel(np.arange(game.n_x))), return_inverse=True)
    result = reach_explicit(game, automaton, cell_class.reshape(-1), labelling.class_letters(classes))
    progress(result.iterations, f"ltl product: {result.details['winning_product_states']:,} of "
             f"{result.details['product_states']:,} product states winning, {result.domain_states:,} domain cells")
    report = {"build_seconds": game.build_seconds, "fixed_point_seconds": result.seconds, "game": game.describe(),
              "results": {"ltl": result.summary()}}
    subsystem = network.subsystems[0].name

    def make(r: ProductResult, meta: dict[str, Any]) -> ProductController:
        return ProductController.from_explicit(r, labelling, {**meta, "subsystem": subsystem})

    return {"ltl": result}, report, make


def partitioning(options: Any, client: Any = None) -> dict[str, Any]:
    """Where and on which engine the fixed points' ``∃u.CPre`` runs: :func:`~pipelines.synthesis.synthesize.synthesize`'s
    ``partitioned``, :class:`~pipelines.synthesis.options.SynthesisOptions`'s ``auto_parts`` and the ``engine``,
    from the job's options and its client.

    ``synthesis_engine``: ``oxidd`` (``auto`` where it is installed and ``synthesis_on`` is ``auto``) runs the
    calls in the job's process on oxidd's threads, one per core, from when
    :meth:`~pipelines.synthesis.engine_cpre.OnOxidd.starts` says (on one machine threads beat parts: consensus N = 8
    about 2.2x two Dask workers). ``cudd`` splits the calls:
    ``synthesis_on: cluster`` needs a client (a job run in process has none: a :class:`SpecError` says so); ``auto``
    uses the client when there is one. On the cluster ``synthesis_processes: 'auto'`` is one part per worker
    thread (:func:`workers.dask_cpre.parts_for`), an int that many parts, and ``1`` one process.
    """
    where, engine = options.synthesis_on, options.synthesis_engine
    if engine == "oxidd" and where != "auto":
        raise SpecError(f"options.synthesis_engine 'oxidd' runs the synthesis in the job's process on threads, but "
                        f"synthesis_on '{where}' asks for CUDD's parts elsewhere: set one of them to 'auto' (or "
                        "synthesis_engine to 'cudd')")
    try:
        engine = resolve_engine("cudd" if engine == "auto" and where != "auto" else engine)
    except ValueError as exc:
        raise SpecError(f"options.synthesis_engine: {exc}") from None
    if engine == "oxidd":
        return {"partitioned": OnOxidd(), "auto_parts": None, "engine": engine}
    if where == "cluster" and client is None:
        raise SpecError("options.synthesis_on is 'cluster' but this job has no Dask cluster (it runs in process): "
                        "run it on a cluster or set synthesis_on to 'auto' or 'processes'")
    if client is not None and where in ("auto", "cluster"):
        return {"partitioned": on_cluster(client), "auto_parts": parts_for(client), "engine": engine}
    return {"partitioned": PartitionedPredecessors, "auto_parts": None, "engine": engine}


#: What to try when no controller exists on the abstraction (the finer the abstraction, the larger the domain).
EMPTY_DOMAIN = ("the winning domain is empty: no controller exists on this abstraction; try a finer grid (eta), "
                "more samples, the 'hull' growth bound or a larger {regions}")


def synthesis_warnings(
    kind: str, main_key: str, domain_states: dict[str, int], initial_states: list[dict[str, Any]], *,
    has_safe: bool = False, quotient: int = 0,
) -> list[str]:
    """What a user should know about a synthesis that ran: an empty winning domain, a reach-and-stay fixed point
    other than the saved one that found a domain, initial states outside the domain, a domain from a quotient.

    Parameters
    ----------
    kind : str
        The specification's kind.
    main_key : str
        The result the controller was made of (a key of ``domain_states``).
    domain_states : dict of str to int
        Winning states by fixed point.
    initial_states : list of dict
        :attr:`~pipelines.verification.closed_loop.ClosedLoop.initial_states` (``x0``, ``in_domain``), in the
        order of ``options.initial_states``.
    has_safe : bool
        Whether the specification restricts runs to a safe set (then that set is one to enlarge).
    quotient : int
        ``options.synthesis_quotient`` (0: the exact fixed points).

    Returns
    -------
    list of str
        One line each; empty if there is nothing to say.
    """
    out = []
    if domain_states[main_key] == 0:
        regions = {"safe": "safe set", "reach": "target", "reach_avoid": "target or a smaller avoid set",
                   "reach_and_stay": "target", "ltl": "formula's regions (or a weaker formula)"}[kind]
        if has_safe and kind != "safe":
            regions += " or safe set"
        line = EMPTY_DOMAIN.format(regions=regions)
        others = {k: n for k, n in domain_states.items() if k != main_key and n > 0}
        if others:
            best = max(others, key=others.__getitem__)
            line += (f"; the {best} fixed point found {others[best]:,} winning states: set options.controller: "
                     f"{best} to use it")
        out.append(line)
    outside = [(i, rec["x0"]) for i, rec in enumerate(initial_states) if not rec["in_domain"]]
    if outside:
        named = ", ".join(f"options.initial_states[{i}] = {x0}" for i, x0 in outside[:10])
        more = f" and {len(outside) - 10} more" if len(outside) > 10 else ""
        out.append(f"{len(outside)} of {len(initial_states)} initial states lie outside the winning domain, so no "
                   f"controller run starts from them and nothing is guaranteed there: {named}{more}")
    if quotient:
        out.append(f"options.synthesis_quotient is {quotient}: the fixed points ran on blocks of {2 ** quotient} cells "
                   "per state coordinate, so the controller is sound but its domain may be smaller than the "
                   "abstraction's maximal one (synthesis.domain_bound bounds that from above); 0 computes the "
                   "maximal domain")
    return out
