"""The cost model: every knob of a spec that multiplies work or memory, and the caps that bound them.

A spec of one kilobyte can ask for hours of work or gigabytes of memory (``lipschitz.pairs: 100000``,
``options.chunk_cells: 1``, ``options.audit_transitions: 1e8``). Every such knob is computed here from the spec
and its built network, before anything is evaluated, and compared with a cap (:class:`Caps`): the service refuses
a job over a cap before it is queued (422, :func:`service.manager.validate_spec`), ``compabs validate`` and
``compabs run`` refuse it before any work starts. Pure: no I/O, no black-box evaluation (the operator's settings
are read by :mod:`service.settings`).

The knobs, each with its cap (:class:`Caps` field; ``COMPABS_<NAME>`` for the service and the command line):

``max_subsystems``
    Subsystems after ``replicate`` is expanded (checked before the network is built: :func:`check_spec`).
``max_expression_length``
    Characters of each ``dynamics`` and of ``interconnection.map`` (checked before the network is built).
``max_cells``
    ``(x, u, w)`` triples of one subsystem: state cells x input points x internal cells (the size of its
    relation). The spec's own ``options.max_cells`` applies too; the smaller cap is named.
``max_evaluations``
    Black-box evaluations of the per-cell stage: triples x ``samples`` x evaluations per step, summed over the
    distinct subsystems (identical replicas are abstracted once).
``max_tasks``
    Tasks of the per-cell stage, summed over the distinct subsystems: ``ceil(state cells / chunk)`` with
    ``options.chunk_cells`` or the default chunk (:func:`pipelines.abstraction.relation.chunk_ranges`). A cluster
    receives them all at once.
``max_lipschitz_pairs``
    Pairs Algorithm 4 draws for one estimated constant (``lipschitz.x`` or ``.w: estimate``) of one distinct
    subsystem, each weighted by the evaluations of one step: ``batches x pairs x input points x rounds x
    evaluations per step``, one round for a scalar and ``1 + d`` for a matrix of ``d`` coordinates (the norm, then
    each coordinate's entries: :func:`~pipelines.abstraction.lipschitz.estimation_rounds`); a round's pairs are
    held in memory at once (~90 bytes a pair for a scalar system).
``max_sample_values``
    The largest array of sampled composed states of the interconnection stage: ``max(samples, holdout) x n``
    (``n`` the composed state dimension).
``max_interconnection_values``
    State values the interconnection stage evaluates the map on or fits: ``n x (samples x (1 + p) + holdout x
    (n + 2p + 4))`` (``p`` internal variables): the lasso's ``p`` fits, the dependence test's ``n + 1`` batches of
    ``holdout`` states, the support validation's ``2p``, the held-out errors and the ``L_M`` check. The
    ``certify`` and ``direct`` steps depend on the learned supports (known only after sampling); they are bounded
    at run time (``MAX_CERTIFY_CELLS``, ``MAX_NODE_ENTRIES``).
``max_audit_evaluations``
    Black-box evaluations of the audit: ``options.audit_transitions`` for each distinct subsystem and for the
    interconnection, plus the composed transitions (a tenth, at least ``min(count, 10^4)``) times every
    subsystem and the map; a subsystem's transition counts its evaluations per step.
``max_closed_loop_steps``
    Subsystem steps of the closed loop (only with ``options.synthesis``): ``(closed_loop_runs + initial_states) x
    closed_loop_steps x subsystems``, each subsystem's step counting its evaluations per step. Automatic steps
    (``closed_loop_steps: null``) depend on the fixed point and are counted as their least, ``AUTO_STEPS_MIN``.

*Evaluations per step*: 1 for a discrete-time map (``dynamics``), ``4 x substeps`` for an ``ode`` (one per
Runge-Kutta 4 stage of each substep, :attr:`~pipelines.spec.model.SubsystemSpec.rhs_evaluations`): every cost
that evaluates a subsystem's black box counts them, so ``substeps: 1000`` costs 1000 times ``substeps: 1``.

Entry points: :func:`check_spec` (before ``build_network``), :func:`check_costs` (everything, returns a summary
line), :func:`estimate_costs` (every knob's value, for reports and tests). A knob over its cap raises
:class:`CostError`, a :class:`~pipelines.errors.SpecError` whose message names the knob (the spec's field path),
its value, the cap and how to get under it.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass, fields, replace
from functools import partial
from typing import Any

from pipelines.abstraction.lipschitz import estimation_rounds
from pipelines.abstraction.relation import DEFAULT_CHUNK_POINTS, default_chunk_cells
from pipelines.errors import SpecError
from pipelines.network import Network, Subsystem, replicate_count
from pipelines.spec.model import JobSpec
from pipelines.verification.audit import composition_transitions

#: Steps of a closed-loop run when ``closed_loop_steps`` is automatic, at the least (``2 * iterations + 30``).
AUTO_STEPS_MIN = 30
#: Environment variables of the caps: ``COMPABS_`` + the field's name in upper case.
ENV_PREFIX = "COMPABS_"


@dataclass(frozen=True)
class Caps:
    """The caps of the cost model. The defaults are the service's (``COMPABS_*`` settings override them);
    :meth:`local` gives the command line's, larger but still bounded.

    ``owner`` says whose caps they are in messages ("this server's cap max_cells is ..."); ``env_hint``, whether
    messages name the variable that sets each (``COMPABS_MAX_CELLS``): true where the caps were read from them.
    """

    max_subsystems: int = 256
    max_expression_length: int = 2000
    max_cells: int = 10_000_000
    max_evaluations: int = 100_000_000_000
    max_tasks: int = 10_000
    max_lipschitz_pairs: int = 2_000_000
    max_sample_values: int = 20_000_000
    max_interconnection_values: int = 1_000_000_000
    max_audit_evaluations: int = 100_000_000
    max_closed_loop_steps: int = 10_000_000
    owner: str = "this server's"
    env_hint: bool = True

    def __post_init__(self) -> None:
        for name in CAP_NAMES:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise SpecError(f"cap {name} must be a positive integer, got {v!r}")

    @classmethod
    def local(cls, **overrides: Any) -> Caps:
        """The command line's caps (``compabs run``, ``compabs validate``): hours of work and a few GB at most."""
        return replace(LOCAL_CAPS, **overrides)

    def values(self) -> dict[str, int]:
        """The caps by name (``max_cells`` ...), without ``owner`` and ``env_hint``."""
        return {name: getattr(self, name) for name in CAP_NAMES}


#: Names of the caps (the :class:`Caps` fields ``max_*``), in the order they are checked.
CAP_NAMES: tuple[str, ...] = tuple(f.name for f in fields(Caps) if f.name.startswith("max_"))

#: The command line's caps: a local user's own machine, so larger; still bounded (a typo must not take hours).
LOCAL_CAPS = Caps(
    max_subsystems=100_000,  # pipelines.network.MAX_REPLICAS
    max_expression_length=4000,  # what the expression compiler accepts
    max_cells=50_000_000,  # options.max_cells' default
    max_evaluations=1_000_000_000_000,
    max_tasks=100_000,
    max_lipschitz_pairs=20_000_000,
    max_sample_values=200_000_000,
    max_interconnection_values=100_000_000_000,
    max_audit_evaluations=10_000_000_000,
    max_closed_loop_steps=100_000_000,
    owner="the local",
    env_hint=False,  # service.settings.local_caps() reads the variables (and sets it)
)


class CostError(SpecError):
    """A knob of the spec over its cap.

    Attributes
    ----------
    knob : str
        The spec's field path(s) (``subsystems[0].lipschitz.batches × subsystems[0].lipschitz.pairs``).
    value : int
        The knob's value, in the cap's unit.
    cap : int
        The cap's value.
    cap_name : str
        The cap (``max_lipschitz_pairs``; ``options.max_cells`` for the spec's own).
    """

    def __init__(self, knob: str, value: int, cap: int, cap_name: str, message: str) -> None:
        super().__init__(message)
        self.knob = knob
        self.value = value
        self.cap = cap
        self.cap_name = cap_name
        self.message = message


@dataclass(frozen=True)
class Cost:
    """One knob's value: ``what`` explains it (starting with the field path), ``fix(cap)`` says how to get under
    ``cap``. ``own_cap`` is a cap the spec itself sets (``options.max_cells``), if any."""

    cap_name: str
    knob: str
    value: int
    what: str
    fix: Callable[[int], str]
    own_cap: int | None = None


def _says(text: str) -> Callable[[int], str]:
    return lambda cap: text


# ====================================================================================== the knobs
def subsystem_count(spec: JobSpec) -> float:
    """Subsystems after ``replicate`` (a parameter that is not defined counts 1: ``build_network`` names it)."""
    total = 0.0
    for s in spec.subsystems:
        try:
            count = float(replicate_count(s, dict(spec.parameters)))
        except SpecError:
            count = 1.0
        total += max(count, 0.0) if math.isfinite(count) else math.inf
    return total


def spec_costs(spec: JobSpec) -> list[Cost]:
    """The knobs known before the network is built: subsystems after ``replicate``, expression lengths."""
    n = subsystem_count(spec)
    shown = f"{int(n)}" if math.isfinite(n) and n == int(n) else f"{n:g}"
    knob = ", ".join(f"subsystems[{i}].replicate" for i, s in enumerate(spec.subsystems) if s.replicate != 1)
    knob = knob or "subsystems"
    named = sorted({f"parameters.{name}" for s in spec.subsystems if isinstance(s.replicate, str)
                    for name in re.findall(r"[A-Za-z_][A-Za-z0-9_]*", s.replicate) if name in spec.parameters})
    costs = [Cost(
        "max_subsystems", knob, int(n) if math.isfinite(n) else 2**63,
        f"{knob}{' (' + ', '.join(named) + ')' if named else ''}: the spec has {shown} subsystems after replicate",
        _says("lower replicate, or the parameter it names"),
    )]
    exprs = [(f"subsystems[{i}].{'dynamics' if s.ode is None else 'ode'}", s.source)
             for i, s in enumerate(spec.subsystems)]
    if spec.interconnection is not None:
        exprs.append(("interconnection.map", spec.interconnection.map))
    for where, text in exprs:
        costs.append(Cost("max_expression_length", where, len(text), f"{where} is {len(text)} characters",
                          _says("shorten it (a parameter can name a repeated number)")))
    return costs


def _index(spec: JobSpec, sub: Subsystem) -> int:
    """The index in ``spec.subsystems`` of the entry ``sub`` was built from."""
    for i, s in enumerate(spec.subsystems):
        if s is sub.spec:
            return i
    return spec.subsystems.index(sub.spec)


def chunk_count(sub: Subsystem, chunk_cells: int | None, task_points: int = DEFAULT_CHUNK_POINTS) -> tuple[int, int]:
    """``(tasks, cells per task)`` of a subsystem's per-cell stage: ``len(chunk_ranges(...))`` without the list."""
    n_x = sub.state_grid.size
    if chunk_cells is None:
        chunk_cells = default_chunk_cells(sub, task_points)
    return -(-n_x // chunk_cells), chunk_cells


def _mb(values: int) -> str:
    mb = values * 8 // 2**20  # integers: a value of 10^600 must not overflow a float
    return f"≈ {mb:,} MB" if mb < 10**9 else "≈ more than a petabyte"


def _cell_costs(spec: JobSpec, groups: list[Subsystem], task_points: int) -> list[Cost]:
    costs = []
    for sub in groups:
        i = _index(spec, sub)
        knob = f"subsystems[{i}].state × subsystems[{i}].input" + (" × interconnection.internal" if sub.reads else "")
        costs.append(Cost(
            "max_cells", knob, sub.triples,
            f"{knob}: subsystem '{sub.name}' has {sub.triples} (x, u, w) cell triples ({sub.state_grid.size} states x "
            f"{sub.input_grid.size} inputs x {sub.n_w_cells} internal cells)",
            _says("coarsen its grids (larger eta, smaller boxes)"), own_cap=spec.options.max_cells,
        ))
    parts = sorted(((s.triples * s.spec.samples * s.spec.rhs_evaluations, s) for s in groups), key=lambda t: -t[0])
    total = sum(v for v, _ in parts)
    shown = "; ".join(f"'{s.name}': {s.triples} triples x {s.spec.samples} samples (subsystems[{_index(spec, s)}]"
                      f".samples)" + (f" x {s.spec.rhs_evaluations} right-hand-side evaluations per sampled step"
                                      if s.spec.ode is not None else "") for _, s in parts[:3])
    top = parts[0][1]
    costs.append(Cost(
        "max_evaluations", "subsystems[*].samples × (x, u, w) triples", total,
        f"subsystems[*].samples × (x, u, w) triples: the per-cell stage evaluates the dynamics {total} times "
        f"({shown})",
        _says(f"lower subsystems[{_index(spec, top)}].samples or coarsen the grids of '{top.name}'"),
    ))
    chunk_cells = spec.options.chunk_cells
    counts = [(chunk_count(s, chunk_cells, task_points), s) for s in groups]
    tasks = sum(c for (c, _), _ in counts)
    cells = sum(s.state_grid.size for s in groups)
    shown = "; ".join(f"'{s.name}': {s.state_grid.size} state cells, {k} per task" for (_, k), s in counts[:3])
    knob = "options.chunk_cells" if chunk_cells is not None else "tasks per job (options.chunk_cells: default)"
    setting = f"options.chunk_cells = {chunk_cells}" if chunk_cells is not None else "the default chunk size"
    costs.append(Cost(
        "max_tasks", knob, tasks,
        f"{knob}: with {setting} the per-cell stage runs {tasks} tasks ({shown})",
        lambda cap: _tasks_fix(cells, len(groups), cap),
    ))
    return costs


def _lipschitz_costs(spec: JobSpec, groups: list[Subsystem]) -> list[Cost]:
    costs = []
    for sub in groups:
        i = _index(spec, sub)
        lip = sub.spec.lipschitz
        for arg in ("x", "w"):
            grid = sub.state_grid if arg == "x" else sub.internal_grid
            if getattr(lip, arg) != "estimate" or grid is None:
                continue
            other = sub.internal_grid if arg == "x" else sub.state_grid
            n_u = sub.input_grid.size
            steps = sub.spec.rhs_evaluations
            pairs = lip.batches * lip.pairs * n_u
            rounds = estimation_rounds(sub.n, grid.dim)
            value = pairs * rounds * steps
            width = 3 * grid.dim + (other.dim if other is not None else 0) + sub.m + 3 * sub.n + 3
            most = (lip.batches, lip.pairs)
            field = f"subsystems[{i}].lipschitz"
            # A matrix is estimated entry by entry: one more round of the same pairs per coordinate.
            per_entry = (f", in {rounds} rounds (the norm, then each of the {grid.dim} coordinates of {arg} for the "
                         f"{sub.n} x {grid.dim} entries) = {pairs * rounds} pairs" if rounds > 1 else "")
            ode = (f" x {steps} evaluations per step (4 x subsystems[{i}].substeps) = {value}"
                   if sub.spec.ode is not None else "")
            costs.append(Cost(
                "max_lipschitz_pairs", f"{field}.batches × {field}.pairs", value,
                f"{field}.batches × {field}.pairs: estimating L_{arg} of subsystem '{sub.name}' draws batches x "
                f"pairs x input points = {most[0]} x {most[1]} x {n_u} = {pairs} pairs at once "
                f"({_mb(pairs * width)}){per_entry}{ode}",
                partial(_lipschitz_fix, field, arg, lip.batches, n_u * rounds * steps, matrix=rounds > 1),
            ))
    return costs


def _interconnection_costs(spec: JobSpec, network: Network) -> list[Cost]:
    ic = spec.interconnection
    if ic is None:  # a single system (or subsystems that read nothing): no interconnection stage
        return []
    n, p = network.state_dim, len(network.internal_grids)
    costs = []
    for which, k in (("samples", ic.samples), ("holdout", ic.holdout)):
        costs.append(Cost(
            "max_sample_values", f"interconnection.{which} × state dimension", k * n,
            f"interconnection.{which} × state dimension: {k} composed states of dimension {n} are {k * n} values in "
            f"one array ({_mb(k * n)})",
            partial(_samples_fix, which, n),
        ))
    value = n * (ic.samples * (1 + p) + ic.holdout * (n + 2 * p + 4))
    costs.append(Cost(
        "max_interconnection_values", "interconnection.samples, interconnection.holdout", value,
        f"interconnection.samples, interconnection.holdout: the interconnection stage evaluates the map on, or fits, "
        f"n x (samples x (1 + p) + holdout x (n + 2p + 4)) = {value} state values (n = {n} states, p = {p} internal "
        f"variables, samples = {ic.samples}, holdout = {ic.holdout})",
        _says("lower interconnection.holdout or interconnection.samples (or use fewer subsystems)"),
    ))
    return costs


def audit_evaluations(count: int, distinct: int, subsystems: int, composition: int | None = None, *,
                      distinct_steps: int | None = None, subsystem_steps: int | None = None) -> int:
    """Black-box evaluations of an audit of ``count`` transitions per part and ``composition`` composed ones
    (default: the job's, :func:`~pipelines.verification.audit.composition_transitions`), as
    :func:`~pipelines.verification.audit.audit_abstraction` draws them.

    ``distinct_steps`` and ``subsystem_steps``: the evaluations of one step summed over the distinct subsystems and
    over all subsystems (1 for a map, ``4 x substeps`` for an ODE); default ``distinct`` and ``subsystems`` (maps).
    """
    if count <= 0:
        return 0
    if composition is None:
        composition = composition_transitions(count)
    d = distinct if distinct_steps is None else distinct_steps
    n = subsystems if subsystem_steps is None else subsystem_steps
    return count * (d + 1) + composition * (n + 1)


def _steps(subs: Iterable[Subsystem]) -> int:
    """The evaluations of one step of each of ``subs``, summed (1 for a map, ``4 x substeps`` for an ODE)."""
    return sum(s.spec.rhs_evaluations for s in subs)


def _ode_note(subs: Iterable[Subsystem]) -> str:
    """What the ODE subsystems among ``subs`` add to a count of evaluations, or ``""``."""
    odes = {s.spec.name: s.spec.rhs_evaluations for s in subs if s.spec.ode is not None}
    if not odes:
        return ""
    shown = ", ".join(f"'{name}': {k}" for name, k in list(odes.items())[:3])
    return f"; an ODE's step counts 4 x substeps evaluations ({shown})"


def _tail_costs(spec: JobSpec, network: Network, groups: list[Subsystem]) -> list[Cost]:
    opts = spec.options
    distinct, subs = len(groups), len(network.subsystems)
    d_steps, n_steps = _steps(groups), _steps(network.subsystems)
    note = _ode_note(network.subsystems)
    count = opts.audit_transitions
    audit = audit_evaluations(count, distinct, subs, distinct_steps=d_steps, subsystem_steps=n_steps)
    composition = composition_transitions(count)
    costs = [Cost(
        "max_audit_evaluations", "options.audit_transitions", audit,
        f"options.audit_transitions = {count} means {audit} black-box evaluations in the audit ({count} for each of "
        f"{distinct} distinct subsystems and the interconnection, {composition} composed transitions x {subs + 1} "
        f"black boxes{note})",
        lambda cap: _audit_fix(count, distinct, subs, cap, d_steps, n_steps),
    )]
    if opts.synthesis:
        runs = opts.closed_loop_runs + len(opts.initial_states)
        steps = opts.closed_loop_steps or AUTO_STEPS_MIN
        how = "" if opts.closed_loop_steps else f" (automatic: at least {AUTO_STEPS_MIN})"
        value = runs * steps * n_steps
        if n_steps == subs:
            per, unit = f"{subs}", "subsystem steps"
        else:
            per, unit = f"{n_steps} evaluations per step of the {subs} subsystems", f"black-box evaluations{note}"
        costs.append(Cost(
            "max_closed_loop_steps", "options.closed_loop_runs × options.closed_loop_steps", value,
            f"options.closed_loop_runs × options.closed_loop_steps: the closed loop simulates (runs + initial states) "
            f"x steps x subsystems = ({opts.closed_loop_runs} + {len(opts.initial_states)}) x {steps}{how} x {per} = "
            f"{value} {unit}",
            lambda cap: _closed_loop_fix(runs, n_steps, cap),
        ))
    return costs


def estimate_costs(spec: JobSpec, network: Network, task_points: int | None = None) -> list[Cost]:
    """Every knob's value, in the order :func:`check_costs` checks them.

    ``task_points``: black-box evaluations per task of the default chunk size (the executor's ``chunk_points``;
    default :data:`~pipelines.abstraction.relation.DEFAULT_CHUNK_POINTS`, the in-process size, which gives the
    most tasks).
    """
    groups = [members[0] for members in network.unique_subsystems().values()]
    points = DEFAULT_CHUNK_POINTS if task_points is None else task_points
    return (spec_costs(spec) + _cell_costs(spec, groups, points) + _lipschitz_costs(spec, groups)
            + _interconnection_costs(spec, network) + _tail_costs(spec, network, groups))


# ====================================================================================== checking
def _tasks_fix(cells: int, groups: int, cap: int) -> str:
    if cap <= groups:
        return "use fewer distinct subsystems (each has at least one task)"
    need = -(-cells // (cap - groups))  # sum ceil(n_g / c) <= cells / c + groups
    return f"set options.chunk_cells to at least {need} (fewer, larger tasks), or coarsen the state grids"


def _lipschitz_fix(field: str, arg: str, batches: int, n_u: int, cap: int, matrix: bool = False) -> str:
    given = f"give L_{arg} as a number or a matrix" if matrix else f"give L_{arg} as a number"
    most = cap // (batches * n_u)
    if most >= 2:
        return (f"lower {field}.pairs to at most {most} with {batches} batches (the defaults are 40 x 200), or "
                f"{given}")
    return f"lower {field}.batches and {field}.pairs (the defaults are 40 x 200), or {given}"


def _samples_fix(which: str, n: int, cap: int) -> str:
    return f"lower interconnection.{which} to at most {cap // n} (or use fewer subsystems)"


def _audit_fix(count: int, distinct: int, subs: int, cap: int, d_steps: int | None = None,
               n_steps: int | None = None) -> str:
    lo, hi = 0, count  # the largest count within the cap (the evaluations grow with it)
    while lo < hi:
        mid = (lo + hi + 1) // 2
        within = audit_evaluations(mid, distinct, subs, distinct_steps=d_steps, subsystem_steps=n_steps) <= cap
        lo, hi = (mid, hi) if within else (lo, mid - 1)
    return f"lower options.audit_transitions to at most {lo} (0: no audit)"


def _closed_loop_fix(runs: int, subs: int, cap: int) -> str:
    if cap >= runs * subs:
        return (f"lower options.closed_loop_runs or options.closed_loop_steps (at most {cap // (runs * subs)} steps "
                f"with {runs} runs)")
    return "lower options.closed_loop_runs (or the number of options.initial_states)"


def _effective(cost: Cost, caps: Caps) -> tuple[int, str, str, str]:
    """The cap that applies to ``cost``: ``(value, name, whose, hint)`` (the spec's own when it is smaller)."""
    cap = getattr(caps, cost.cap_name)
    if cost.own_cap is not None and cost.own_cap < cap:
        return cost.own_cap, f"options.{cost.cap_name}", "the spec's", ""
    return cap, cost.cap_name, caps.owner, f" ({ENV_PREFIX}{cost.cap_name.upper()})" if caps.env_hint else ""


def _over(costs: Iterable[Cost], caps: Caps) -> None:
    for cost in costs:
        cap, name, owner, hint = _effective(cost, caps)
        if cost.value > cap:
            message = f"{cost.what}; {owner} cap {name} is {cap}{hint}: {cost.fix(cap)}"
            raise CostError(cost.knob, cost.value, cap, name, message)


def check_spec(spec: JobSpec, caps: Caps | None = None) -> None:
    """The caps checked before the network is built (``replicate: 1e9`` costs nothing): subsystems, expressions.

    ``caps``: default :meth:`Caps.local`.

    Raises
    ------
    CostError
        Naming the knob, its value and the cap.
    """
    _over(spec_costs(spec), Caps.local() if caps is None else caps)


def check_costs(spec: JobSpec, network: Network, caps: Caps | None = None, *, task_points: int | None = None) -> str:
    """Check every knob against its cap; return a one-line summary (the knob nearest its cap).

    Parameters
    ----------
    spec, network
        The spec and ``build_network(spec, ...)``.
    caps
        Default :meth:`Caps.local` (the command line's); the service passes its settings' (:class:`Caps`).
    task_points
        As for :func:`estimate_costs`.

    Raises
    ------
    CostError
        The first knob over its cap, naming the knob (the spec's field path), its value, the cap and the fix.
    """
    caps = Caps.local() if caps is None else caps
    costs = estimate_costs(spec, network, task_points)
    _over(costs, caps)

    def share(c: Cost) -> float:
        return c.value / _effective(c, caps)[0]

    nearest = max(costs, key=share)
    cap, name, _, _ = _effective(nearest, caps)
    return f"every knob within {caps.owner} caps; nearest: {nearest.knob} = {nearest.value} of {name} {cap} " \
           f"({share(nearest):.0%})"


__all__ = ["AUTO_STEPS_MIN", "CAP_NAMES", "LOCAL_CAPS", "Caps", "Cost", "CostError", "audit_evaluations",
           "check_costs", "check_spec", "chunk_count", "estimate_costs", "spec_costs", "subsystem_count"]
