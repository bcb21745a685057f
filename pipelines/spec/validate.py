"""Every check of a job spec that needs no black-box evaluation: what ``compabs validate`` prints and what
:func:`workers.job.run_job` runs before it creates the job's directory or starts a cluster.

Pure (no file or network I/O), so the command line, the orchestrator and the service share it. The checks, in
order, each giving one line of :attr:`Validation.lines` or raising a :class:`~pipelines.errors.SpecError` that
names the field:

1. ``parameters``: those overridden by ``--set`` exist in the spec (:func:`check_overrides`, called by
   :func:`pipelines.spec.model.load_spec` before the overrides are applied) and are finite;
2. ``network``: the network builds: grids non-empty, ``replicate`` counts, ``reads``, and every expression
   compiled against its declared dimensions (the one-point probe that infers a map's output dimension is the
   only evaluation, as when the job itself starts);
3. ``cells``: every subsystem's ``(x, u, w)`` triples within ``options.max_cells``;
4. ``options.initial_states``: each has the state dimension and finite components;
5. ``specification.*``: every region of the specification contains a whole cell (targets and safe sets from
   inside) or meets one (sets to avoid); for ``ltl``, the formula parses within its fragment, names only its
   regions and uses each, and every region meets a cell (:func:`check_formula`; MONA's translation, which can take
   seconds, is the job's and ``compabs validate``'s: :func:`workers.automata.translate`);
6. ``caps``: every knob of the cost model (:mod:`pipelines.spec.costs`) within its cap: subsystems after
   ``replicate`` and expression lengths before the network is built (:func:`~pipelines.spec.costs.check_spec`),
   the rest after (:func:`~pipelines.spec.costs.check_costs`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from pipelines.abstraction.lipschitz import check_given_constants
from pipelines.errors import SpecError
from pipelines.network import Network, build_network
from pipelines.spec.costs import Caps, check_costs, check_spec
from pipelines.spec.model import JobSpec, check_overrides, parse_spec
from pipelines.spec.regions import AbstractRegion, spec_regions, union_count


@dataclass(frozen=True)
class Validation:
    """The outcome of :func:`validate_spec`: what was built, and one line per check (``"<check>: <result>"``)."""

    spec: JobSpec
    network: Network
    regions: dict[str, AbstractRegion]
    lines: tuple[str, ...]


def with_options(spec: JobSpec, **updates: Any) -> JobSpec:
    """``spec`` with some ``options`` replaced, validated like the spec's own (a command-line override such as
    ``--audit-transitions`` gets the field's bounds, not a silent ``model_copy``).

    Raises
    ------
    SpecError
        Naming the option and its bound.
    """
    data = spec.model_dump(mode="json")
    data["options"] = {**data["options"], **updates}
    return parse_spec(data)


def usable_cpus() -> int:
    """The cores this process may run on (its CPU affinity; ``os.cpu_count()`` where that is unknown)."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def cap_synthesis_processes(spec: JobSpec, *, on_cluster: bool, cpus: int | None = None) -> JobSpec:
    """``spec`` with ``options.synthesis_processes`` at most the cores present (``cpus``, default
    :func:`usable_cpus`) where the synthesis parts would run as helper processes on this machine
    (``synthesis_on: processes``, or ``auto`` without a cluster). More processes than cores only share them, at a
    copy of the problem each (``synthesis_processes: 64`` on 2 cores started 56 helpers, 3.5 GB); on a cluster the
    number is the parts' count, left as given. Results do not depend on it (not part of the spec's hash)."""
    options = spec.options
    n = options.synthesis_processes
    local = options.synthesis_on == "processes" or (options.synthesis_on == "auto" and not on_cluster)
    cpus = usable_cpus() if cpus is None else max(1, cpus)
    if n == "auto" or not local or n <= cpus:
        return spec
    return with_options(spec, synthesis_processes=cpus)


def check_cells(spec: JobSpec, network: Network) -> str:
    """Every subsystem's ``(x, u, w)`` triples within ``options.max_cells``."""
    cap = spec.options.max_cells
    for s in network.subsystems:
        if s.triples > cap:
            raise SpecError(
                f"subsystem '{s.name}': {s.triples} (x, u, w) triples exceed options.max_cells = {cap}; coarsen its "
                "grids or raise the cap"
            )
    largest = max(network.subsystems, key=lambda s: s.triples)
    return f"cells: at most {largest.triples:,} (x, u, w) triples per subsystem ('{largest.name}'); options.max_cells {cap:,}"


def check_initial_states(spec: JobSpec, network: Network) -> str:
    """Each of ``options.initial_states`` has one finite component per state of the composed system."""
    n = network.state_dim
    states = spec.options.initial_states
    for i, x in enumerate(states):
        if len(x) != n:
            raise SpecError(f"options.initial_states[{i}] has {len(x)} components; the system has {n} states")
        bad = [k for k, v in enumerate(x) if not math.isfinite(v)]
        if bad:
            raise SpecError(f"options.initial_states[{i}][{bad[0]}] is {x[bad[0]]}; a state is finite")
    if not states:
        return "options.initial_states: none given"
    return f"options.initial_states: {len(states)} of dimension {n}"


def _region_lines(regions: Mapping[str, AbstractRegion]) -> list[str]:
    how = {"avoid": "cells meeting it"}
    return [f"specification.{name}: {r.states:,} abstract states ({how.get(name, 'whole cells inside it')})"
            for name, r in regions.items()]


def check_formula(spec: JobSpec, network: Network) -> list[str]:
    """An ``ltl`` specification's formula and regions (nothing for the other kinds): the formula parses, inside
    its fragment, every atom a region (:func:`~pipelines.temporal.formula.parse_formula`), every region is an atom
    of it (an unused region is a mistake, as for the other kinds), and each meets a grid cell; one line per region
    with the cells wholly inside it and those on its edge (docs/spec.md, "Temporal-logic tasks").

    Raises
    ------
    SpecError
        Naming the token and its position, the operator, the atom, or the region.
    """
    specification = spec.specification
    if specification.kind != "ltl":
        return []
    from pipelines.temporal.formula import parse_formula
    from pipelines.temporal.labels import Labelling

    if spec.options.synthesis_quotient:
        raise SpecError("options.synthesis_quotient: an 'ltl' specification is solved on the exact product game; set "
                        "synthesis_quotient to 0")
    regions = specification.regions or {}
    assert specification.formula is not None  # the model requires it for 'ltl'
    formula = parse_formula(specification.formula, regions)
    unused = sorted(set(regions) - set(formula.atoms))
    if unused:
        raise SpecError(f"specification.regions.{unused[0]}: the formula does not use this region; use it in the "
                        "formula or remove it")
    labelling = Labelling.of(formula.atoms, regions, network.composed_state_grid())
    lines = [f"specification.formula: {len(formula.atoms)} atoms ({', '.join(formula.atoms)}), "
             f"{2 ** len(formula.atoms)} letters"]
    for atom, inside, meets in zip(formula.atoms, labelling.inside, labelling.meets):
        if not meets.boxes:
            raise SpecError(f"specification.regions.{atom}: the region meets no grid cell (it lies outside the state "
                            "set)")
        edge = meets.states - inside.states
        lines.append(f"specification.regions.{atom}: {inside.states:,} abstract states wholly inside it, {edge:,} on "
                     "its edge")
    return lines


def check_contracts(spec: JobSpec, network: Network, regions: Mapping[str, AbstractRegion]) -> list[str]:
    """``options.fixed_points: [contracts]`` (reach-and-stay and safety; nothing otherwise): a network of at least two
    subsystems, the exact game (no quotient), and a target and safe set that are products of one set per subsystem
    (:mod:`pipelines.synthesis.contracts`): a union of boxes is one exactly when it holds as many cells as the
    product of its projections.

    Raises
    ------
    SpecError
        Naming the field and what to change.
    """
    if spec.specification.kind not in ("reach_and_stay", "safe") or "contracts" not in spec.options.fixed_points:
        return []
    if len(network.subsystems) < 2:
        raise SpecError("options.fixed_points: 'contracts' split a network into one game per subsystem, and this "
                        "system has one subsystem: use reach_safe or cobuchi (its exact game is small)")
    if spec.options.synthesis_quotient:
        raise SpecError("options.synthesis_quotient: 'contracts' solve one exact game per subsystem; set "
                        "synthesis_quotient to 0 or leave contracts out of options.fixed_points")
    for name in ("target", "safe"):
        region = regions.get(name)
        if region is None:
            continue
        projections = 1
        for s in network.subsystems:
            cut = slice(s.state_offset, s.state_offset + s.n)
            projections *= union_count([(lo[cut], hi[cut]) for lo, hi in region.boxes])
        if projections != region.states:
            raise SpecError(f"specification.{name}: 'contracts' need a set that is a product of one set per "
                            f"subsystem, and this one holds {region.states:,} of the {projections:,} cells of the "
                            "product of its projections: give one box, or boxes that differ in one subsystem's "
                            "coordinates only, or leave contracts out of options.fixed_points")
    return [f"options.fixed_points: contracts, {len(network.subsystems)} local games on products of per-subsystem "
            "sets"]


def check_caps(spec: JobSpec, network: Network, caps: Caps | None = None) -> str:
    """Every knob of the cost model within its cap (:func:`pipelines.spec.costs.check_costs`; ``caps``: default
    the command line's, :meth:`~pipelines.spec.costs.Caps.local`).

    Raises
    ------
    CostError
        The first knob over its cap, naming the knob (field path), its value, the cap and the fix.
    """
    return f"caps: {check_costs(spec, network, caps)}"


def validate_spec(spec: JobSpec, *, allowed_modules: Sequence[str] | None = (), caps: Caps | None = None) -> Validation:
    """Run every check that needs no black-box evaluation (the module docstring lists them).

    Parameters
    ----------
    spec : JobSpec
        As parsed (:func:`~pipelines.spec.model.parse_spec`, :func:`~pipelines.spec.model.load_spec`), overrides
        applied.
    allowed_modules
        Modules a ``module:function`` may name, as for :func:`~pipelines.network.build_network` (``None``: any,
        the local command line; the default ``()``: none).
    caps
        The cost model's caps (:class:`~pipelines.spec.costs.Caps`; ``None``: the command line's,
        :meth:`~pipelines.spec.costs.Caps.local`; the service passes its settings').

    Raises
    ------
    SpecError
        The first check that fails, naming the field (and index) at fault (a
        :class:`~pipelines.spec.costs.CostError` for a knob over its cap).
    """
    params = ", ".join(f"{k} = {v:g}" for k, v in spec.parameters.items()) or "none"
    lines = [f"spec: '{spec.name}' parses", f"parameters: {params}"]
    check_spec(spec, caps)  # subsystems after replicate, expression lengths: before anything is built
    network = build_network(spec, allowed_modules)
    for members in network.unique_subsystems().values():
        check_given_constants(members[0])
    distinct = len(network.unique_subsystems())
    lines.append(
        f"network: {len(network.subsystems)} subsystems ({distinct} distinct), {network.state_dim} states, "
        f"{len(network.internal_grids)} internal variables, {network.abstract_states:,} abstract states; "
        "expressions compile"
    )
    lines.append(check_cells(spec, network))
    lines.append(check_initial_states(spec, network))
    regions = spec_regions(spec, network)
    lines += _region_lines(regions)
    lines += check_formula(spec, network)
    lines += check_contracts(spec, network, regions)
    lines.append(check_caps(spec, network, caps))
    return Validation(spec, network, regions, tuple(lines))


__all__ = ["Validation", "cap_synthesis_processes", "check_caps", "check_cells", "check_contracts", "check_formula",
           "check_initial_states",
           "check_overrides",
           "validate_spec", "with_options"]
