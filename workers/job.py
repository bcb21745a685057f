"""The stages of a job, defined once (ARCHITECTURE "The job, as data flowing through").

``run_abstraction`` takes a spec through plan -> Lipschitz constants -> subsystem abstractions (Algorithm 1)
-> interconnection abstraction (Algorithms 2-3) -> audit, and returns the artefacts and the report. How the
per-chunk tasks run is a parameter: ``mapper(fn, args_list)`` returns the results of ``fn(*args)`` for each
argument tuple, in-process by default; the distributed runner passes one backed by a Dask client.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from pipelines.verification.audit import AuditResult, audit_composition, audit_interconnection, audit_subsystem
from pipelines.errors import LipschitzError
from pipelines.abstraction.lipschitz import estimate_lipschitz
from pipelines.network import Network, Subsystem, build_network
from pipelines.spec.regions import AbstractRegion, abstract_region
from pipelines.spec.model import JobSpec, spec_hash
from pipelines.abstraction.cells import SLOPE_RTOL, CellsResult, SubsystemRelation, abstract_cells, assemble, chunk_ranges

Progress = Callable[[str, int, int, str], None]
Mapper = Callable[[Callable[..., Any], Sequence[tuple]], Iterable[Any]]

STAGES = ("plan", "lipschitz", "subsystems", "interconnection", "audit")


def local_mapper(fn: Callable[..., Any], args: Sequence[tuple]) -> Iterable[Any]:
    """Run tasks one after another in this process."""
    for a in args:
        yield fn(*a)


def _no_progress(stage: str, done: int, total: int, message: str) -> None:
    return None


@dataclass
class ConstantRecord:
    """A Lipschitz constant and where it came from (for the report)."""

    value: float
    source: str  # given | raised | estimated
    given: float | None = None
    observed_max_slope: float = 0.0
    where: str = ""
    estimate: dict | None = None

    def as_dict(self) -> dict:
        d = {"value": self.value, "source": self.source, "observed_max_slope": self.observed_max_slope}
        if self.given is not None:
            d["given"] = self.given
            if self.source == "raised":  # how much the data made it grow (METHOD §3: say so in the report)
                d["raised_by"] = self.value - self.given
                d["raised_factor"] = self.value / self.given if self.given > 0 else None
        if self.where:
            d["where"] = self.where
        if self.estimate:
            d["estimate"] = self.estimate
        return d


@dataclass
class AbstractionResult:
    """Everything the abstraction stages produce; the synthesis stages consume it."""

    spec: JobSpec
    network: Network
    relations: dict[str, SubsystemRelation]  # by subsystem key
    interconnection: Any
    target: AbstractRegion | None
    report: dict[str, Any] = field(default_factory=dict)
    pending_audit: Any = field(default=None, repr=False)  # a BackgroundAudit until finish_audit

    def finish_audit(self, progress: Progress = _no_progress) -> None:
        """Wait for an audit started beside synthesis (``run_abstraction(audit_beside=True)``) and put its report
        in ``report["audit"]``; nothing if none is pending. Raises what the audit raised (e.g. a black box that
        returned NaN on an audit sample)."""
        if self.pending_audit is None:
            return
        pending, self.pending_audit = self.pending_audit, None
        audit, seconds, waited = pending.result()
        self.report["audit"] = {**audit, "beside_synthesis": True, "waited_seconds": waited}
        self.report["stage_seconds"]["audit"] = seconds
        progress("audit", 1, 1, f"{audit['transitions_checked']} transitions, {audit['violations']} violations")

    def cancel_audit(self) -> None:
        """Stop an audit started beside synthesis, if one is running (idempotent)."""
        if self.pending_audit is not None:
            pending, self.pending_audit = self.pending_audit, None
            pending.cancel()


def _resolve_constant(sub: Subsystem, arg: str, rng: np.random.Generator) -> ConstantRecord:
    lip = sub.spec.lipschitz
    given = getattr(lip, arg)
    if arg == "w" and sub.internal_grid is None:
        return ConstantRecord(0.0, "unused")
    if given == "estimate":
        est = estimate_lipschitz(sub, arg, rng, lip.batches, lip.pairs, lip.delta, lip.safety_factor)
        return ConstantRecord(
            est.value,
            "estimated",
            observed_max_slope=est.max_slope,
            estimate={"location": est.location, "max_slope": est.max_slope, "safety_factor": lip.safety_factor,
                      "batches": est.batches, "pairs": est.pairs},
        )
    return ConstantRecord(float(given), "given", given=float(given))


def _box(lo: np.ndarray, hi: np.ndarray) -> str:
    return " x ".join(f"[{a:g}, {b:g}]" for a, b in zip(lo, hi))


def _describe_cell(sub: Subsystem, rec) -> str:
    x_lo, x_hi = sub.state_grid.clipped_cells(sub.state_grid.unravel(np.array([rec.x_cell])))
    u = sub.input_grid.points(sub.input_grid.unravel(np.array([rec.u_index])))[0]
    where = f"state cell {rec.x_cell} (x in {_box(x_lo[0], x_hi[0])}), input u={u.tolist()}"
    if sub.internal_grid is not None:
        w_lo, w_hi = sub.internal_grid.clipped_cells(sub.internal_grid.unravel(np.array([rec.w_cell])))
        where += f", internal cell {rec.w_cell} (w in {_box(w_lo[0], w_hi[0])})"
    return where


def _abstract_one(
    sub: Subsystem,
    members: list[Subsystem],
    constants: dict[str, ConstantRecord],
    mapper: Mapper,
    progress: Progress,
    done_before: int,
    total: int,
    chunk_cells: int | None,
    chunk_points: int | None = None,
) -> tuple[SubsystemRelation, dict]:
    """Abstract one (group of identical) subsystem(s), validating the Lipschitz constants on its data."""
    spec = sub.spec
    chunks = chunk_ranges(sub, chunk_cells, chunk_points)
    for attempt in range(2):
        L_x, L_w = constants["x"].value, constants["w"].value
        args = [(sub, a, b, L_x, L_w, spec.growth_bound, spec.scp_objective) for a, b in chunks]
        results: list[CellsResult] = []
        for i, r in enumerate(mapper(abstract_cells, args)):
            results.append(r)
            progress("subsystems", done_before + i + 1, total, f"{sub.name}: chunk {i + 1}/{len(chunks)}")
        # A mapper may yield in any order (a cluster: completion order); merging in cell order makes the
        # reported location of a tied largest slope independent of it.
        results.sort(key=lambda r: r.start)
        slope_x, slope_w = results[0].slope_x, results[0].slope_w
        for r in results[1:]:
            slope_x, slope_w = slope_x.merge(r.slope_x), slope_w.merge(r.slope_w)
        violated = []
        for arg, rec in (("x", slope_x), ("w", slope_w)):
            c = constants[arg]
            c.observed_max_slope = max(c.observed_max_slope, rec.slope)
            if c.source != "unused" and rec.slope > c.value * (1 + SLOPE_RTOL):
                violated.append((arg, rec))
        if not violated:
            break
        names = ", ".join(m.name for m in members)
        for arg, rec in violated:
            c = constants[arg]
            where = _describe_cell(sub, rec)
            if c.source == "given" and spec.lipschitz.on_violation == "fail":
                excess = f", {rec.slope - c.value:.6g} ({rec.slope / c.value - 1:.2%}) above it" if c.value > 0 else ""
                raise LipschitzError(
                    f"subsystem {names}: the given L_{arg} = {c.value:g} is contradicted by the data: slope "
                    f"{rec.slope:.6g} observed at {where}{excess}. An abstraction built with it would be unsound. Give "
                    f"L_{arg} >= {rec.slope:.6g}, set lipschitz.{arg}: estimate, or lipschitz.on_violation: raise."
                )
            c.value = rec.slope * spec.lipschitz.safety_factor
            c.source = "raised" if c.source in ("given", "raised") else "estimated (raised by cell data)"
            c.where = where
    else:  # pragma: no cover - the second pass reuses the same samples, so it cannot be violated again
        raise RuntimeError("Lipschitz constants still violated after raising them")

    rel = assemble(results, sub.state_grid.size, spec.growth_bound, L_x, L_w)
    totals: dict[str, list[int]] = {}
    for r in results:
        for name, (s, k) in r.successors.items():
            t = totals.setdefault(name, [0, 0])
            t[0] += s
            t[1] += k
    mean = {name: (s / k if k else None) for name, (s, k) in totals.items()}
    triples = int(rel.blocking.size)
    info = {
        "name": sub.name,
        "members": [m.name for m in members],
        "growth_bound": spec.growth_bound,
        "scp_objective": spec.scp_objective,
        "triples": triples,
        "chunks": len(chunks),
        "samples_per_cell": spec.samples,
        "blocking_fraction": float(rel.blocking.mean()),
        "mean_successors": mean,
        "non_blocking": {name: k for name, (s, k) in totals.items()},
        "lipschitz": {arg: c.as_dict() for arg, c in constants.items()},
    }
    return rel, info


def spec_regions(spec: JobSpec, network: Network) -> dict[str, AbstractRegion]:
    """The specification's regions on the composed grid: targets and safe sets from inside, avoid sets from
    outside (METHOD §1)."""
    grid = network.composed_state_grid()
    regions: dict[str, AbstractRegion] = {}
    for name in ("target", "safe", "avoid"):
        region = getattr(spec.specification, name)
        if region is not None:
            regions[name] = abstract_region(region, grid, f"specification.{name}", outer=(name == "avoid"))
    return regions


def run_abstraction(
    spec: JobSpec,
    *,
    mapper: Mapper = local_mapper,
    progress: Progress = _no_progress,
    allowed_modules: Sequence[str] | None = None,
    audit: bool = True,
    chunk_points: int | None = None,
    audit_beside: bool = False,
) -> AbstractionResult:
    """Run the abstraction stages of a job and build its report.

    Parameters
    ----------
    spec : JobSpec
    mapper : callable
        ``mapper(fn, [args, ...])`` -> iterable of ``fn(*args)``; in-process by default.
    progress : callable
        ``progress(stage, done, total, message)``, called as work completes.
    allowed_modules
        Modules a ``module:function`` may name (``None``: any, the local command line).
    chunk_points : int, optional
        Black-box evaluations per chunk task when ``options.chunk_cells`` is not set (``None``: the default of
        :func:`~pipelines.abstraction.cells.chunk_ranges`). A runner picks it from its per-task overhead.
    audit_beside : bool
        Start the audit in a child process and return without waiting (:mod:`.audit_beside`): synthesis needs
        nothing the audit makes, so it runs on another core meanwhile. The caller must call
        :meth:`AbstractionResult.finish_audit` (which fills ``report["audit"]``) or ``cancel_audit``.

    Raises
    ------
    CompabsError
        Subclasses name what is wrong: SpecError, ExpressionError, BlackBoxError, LipschitzError,
        CertificationError.
    """
    from pipelines.interconnection.core import abstract_interconnection

    rng = np.random.default_rng(spec.options.seed)
    seconds: dict[str, float] = {}

    t0 = time.perf_counter()
    progress("plan", 0, 1, "building grids")
    network = build_network(spec, allowed_modules)
    for s in network.subsystems:
        if s.triples > spec.options.max_cells:
            from pipelines.errors import SpecError

            raise SpecError(
                f"subsystem '{s.name}': {s.triples} (x, u, w) triples exceed options.max_cells = "
                f"{spec.options.max_cells}; coarsen its grids or raise the cap"
            )
    regions = spec_regions(spec, network)
    groups = network.unique_subsystems()
    progress("plan", 1, 1, f"{len(network.subsystems)} subsystems, {len(groups)} distinct")
    seconds["plan"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    constants: dict[str, dict[str, ConstantRecord]] = {}
    for i, (key, members) in enumerate(groups.items()):
        sub = members[0]
        constants[key] = {arg: _resolve_constant(sub, arg, rng) for arg in ("x", "w")}
        progress("lipschitz", i + 1, len(groups), sub.name)
    seconds["lipschitz"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    relations: dict[str, SubsystemRelation] = {}
    infos = []
    chunk_cells = spec.options.chunk_cells
    total_chunks = sum(len(chunk_ranges(m[0], chunk_cells, chunk_points)) for m in groups.values())
    done = 0
    for key, members in groups.items():
        rel, info = _abstract_one(
            members[0], members, constants[key], mapper, progress, done, total_chunks, chunk_cells, chunk_points
        )
        done += info["chunks"]
        relations[key] = rel
        infos.append(info)
    seconds["subsystems"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    progress("interconnection", 0, 1, "sampling the map")
    ia = abstract_interconnection(network, rng)
    progress("interconnection", 1, 1, f"{len(ia.nodes)} nodes")
    seconds["interconnection"] = time.perf_counter() - t0

    audit_report: dict[str, Any] = {"transitions_checked": 0, "violations": 0}
    pending = None
    if audit and spec.options.audit_transitions:
        if audit_beside:
            from workers.processes.audit_beside import BackgroundAudit

            pending = BackgroundAudit(network, relations, ia, spec.options.audit_transitions, rng)
            audit_report = {"transitions_checked": 0, "violations": 0, "pending": True}
            progress("audit", 0, 1, "running in a child process beside synthesis")
        else:
            t0 = time.perf_counter()
            audit_report = run_audit(network, relations, ia, spec.options.audit_transitions, rng, progress)
            seconds["audit"] = time.perf_counter() - t0

    target = regions.get("target") or regions.get("safe")
    counts = {k: r.states for k, r in regions.items()}  # exact counts cost a sweep each: once per region
    report = {
        "name": spec.name,
        "spec_hash": spec_hash(spec),
        "abstract_states": network.abstract_states,
        "region_states": counts.get("target", counts.get("safe")),
        "regions": {k: {"states": counts[k], "boxes": len(r.boxes)} for k, r in regions.items()},
        "subsystem_count": len(network.subsystems),
        "stage_seconds": seconds,
        "subsystems": infos,
        "interconnection": ia.describe(),
        "audit": audit_report,
    }
    return AbstractionResult(spec, network, relations, ia, target, report, pending_audit=pending)


def run_audit(
    network: Network, relations: dict[str, SubsystemRelation], ia: Any, count: int, rng: np.random.Generator,
    progress: Progress = _no_progress,
) -> dict[str, Any]:
    """The audit stage: Theorems 4.2 and 4.7 and the composition checked on ``count`` random transitions each.

    Returns the report's ``audit`` entry (``transitions_checked``, ``violations``, ``parts``). Draws from ``rng``
    in a fixed order, so the same generator state gives the same report in this process or in a child
    (:mod:`.audit_beside`).
    """
    groups = network.unique_subsystems()
    parts: dict[str, AuditResult] = {}
    total = len(groups) + 2
    for i, (key, members) in enumerate(groups.items()):
        parts[members[0].name] = audit_subsystem(members[0], relations[key], count, rng)
        progress("audit", i + 1, total, members[0].name)
    parts["interconnection"] = audit_interconnection(network, ia, count, rng)
    progress("audit", total - 1, total, "interconnection")
    # The composed system: the same inclusions again, plus the wiring between the parts (which w_j each
    # subsystem reads, offsets, which relation serves which replica). A tenth of the transitions is plenty
    # for that here; `compabs audit DIR --transitions N` draws N of them against the stored abstraction.
    parts["composition"] = audit_composition(network, relations, ia, max(min(count, 10_000), count // 10), rng)
    progress("audit", total, total, "composition")
    return {
        "transitions_checked": sum(p.transitions_checked for p in parts.values()),
        "violations": sum(p.violations for p in parts.values()),
        "parts": {k: p.as_dict() for k, p in parts.items()},
    }


# ====================================================================================== synthesis stages
def _random_domain_states(controller, count: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Concrete states drawn uniformly in cells drawn uniformly from the controller's domain."""
    idx = controller.sample_cells(count, rng)
    if idx.shape[0] == 0:
        return []
    lo, hi = controller.state_grid.clipped_cells(idx)
    return list(rng.uniform(lo, hi))


def run_synthesis(
    abstraction: AbstractionResult,
    out_dir: str | Path | None = None,
    *,
    progress: Progress = _no_progress,
    runs: int | None = None,
) -> dict[str, Any]:
    """Synthesize, save the controller, run the closed loop and draw the figures (METHOD §5-6).

    Returns the report entries: ``domain_states``, ``domain_states_by_fixed_point``, ``controller``,
    ``synthesis``, ``closed_loop`` and ``figures``.
    """

    from pipelines.verification.closed_loop import simulate, simulate_many
    from pipelines.controller import controller_of
    from pipelines.figures import domain_slice_figure, trajectory_figure
    from pipelines.synthesis.game import synthesize

    spec = abstraction.spec
    opts = spec.options
    kind = spec.specification.kind
    t0 = time.perf_counter()
    progress("synthesis", 0, 1, "building BDDs and solving")
    game, results, syn_report = synthesize(abstraction, reach_and_stay_methods=tuple(opts.fixed_points),
                                           processes=opts.synthesis_processes)
    progress("synthesis", 1, 1, ", ".join(f"{k}: {r.domain_states}" for k, r in results.items()))
    seconds = {"synthesis": time.perf_counter() - t0}
    main_key = opts.controller if kind == "reach_and_stay" else next(iter(results))
    main = results[main_key]

    network = abstraction.network
    meta = {
        "kind": kind,
        "fixed_point": main_key,
        "state_grid": network.composed_state_grid().describe(),
        "input_grids": [s.input_grid.describe() for s in network.subsystems],
        "spec": spec.model_dump(mode="json"),
        "domain_states": main.domain_states,
    }
    controller = controller_of(game, main, meta)
    files = {}
    if out_dir is not None:
        from workers.jobdir import save_interconnection

        out = Path(out_dir)
        save_interconnection(abstraction.interconnection, out, spec)  # what the controller was built from (audit)
        files["controller"] = [str(p.name) for p in controller.save(out)]
        for key, r in results.items():
            if key != main_key:
                controller_of(game, r, {**meta, "fixed_point": key, "domain_states": r.domain_states}).save(
                    out, f"controller_{key}"
                )

    # Closed loop (Theorem 4.2): from the spec's initial states in the domain, and from random domain states.
    t0 = time.perf_counter()
    rng = np.random.default_rng(opts.seed + 1)
    n_runs = opts.closed_loop_runs if runs is None else runs
    steps = opts.closed_loop_steps or (2 * (main.iterations + main.inner_iterations) + 30)
    grid = network.composed_state_grid()
    regions = spec_regions(spec, network)
    target = regions.get("target") or regions.get("safe")
    avoid = regions.get("avoid")
    starts: list[tuple[str, np.ndarray]] = []
    paper = []
    for x0 in opts.initial_states:
        x0 = np.asarray(x0, dtype=float)
        idx = controller.cell(x0)
        inside = idx is not None and bool(controller.in_domain(idx[None, :])[0])
        paper.append({"x0": x0.tolist(), "in_domain": inside})
        if inside:
            starts.append(("initial", x0))
    starts += [("random", x) for x in _random_domain_states(controller, n_runs, rng)]
    run_records = []
    violations = 0
    first_violation = None
    runs = simulate_many(network, controller, np.array([x0 for _, x0 in starts]).reshape(len(starts), grid.dim), steps,
                         rng, kind, target, avoid,
                         progress=lambda k, n: progress("closed_loop", k, n, f"{len(starts)} runs in lockstep"))
    for (origin, x0), run in zip(starts, runs):
        if run.violation:
            violations += 1
            first_violation = first_violation or f"from {x0.tolist()}: {run.violation}"
        run_records.append((origin, x0, run))
    for rec in paper:
        for origin, x0, run in run_records:
            if origin == "initial" and np.allclose(x0, rec["x0"]):
                rec.update(violation=run.violation, settled_at=run.settled_at, steps=int(run.inputs.shape[0]))
    settled = [r.settled_at for _, _, r in run_records if r.settled_at is not None]
    closed = {
        "runs": len(run_records),
        "violations": violations,
        "first_violation": first_violation,
        "steps": steps,
        "steps_to_reach": {"min": min(settled), "mean": float(np.mean(settled)), "max": max(settled)} if settled else None,
        "initial_states": paper,
    }
    seconds["closed_loop"] = time.perf_counter() - t0

    figures = []
    if out_dir is not None and run_records:
        out = Path(out_dir)
        origin, x0, run = run_records[0]
        free = simulate(network, None, x0, run.inputs.shape[0] or steps, rng, kind, target, avoid)
        band = None
        if kind in ("reach_and_stay", "reach", "reach_avoid") and spec.specification.target.boxes:
            b = spec.specification.target.boxes[0]
            lb, ub = np.atleast_1d(b.lb), np.atleast_1d(b.ub)
            band = (float(lb.min()), float(ub.max()))
        figures.append(trajectory_figure(run, free, out / "trajectory.png", f"{spec.name} from {np.round(x0, 1).tolist()}", band).name)
        idx = controller.cell(x0)
        if grid.dim >= 2 and idx is not None:
            figures.append(domain_slice_figure(
                controller.in_domain, grid.axis_points(0), grid.axis_points(1), idx, 0, 1,
                out / "domain_slice.png", f"{spec.name}: domain on (x1, x2), others at the cell of x0",
            ).name)
        (out / "closed_loop_example.json").write_text(json.dumps({"controlled": run.as_dict(), "free": free.as_dict()}))

    return {
        "domain_states": main.domain_states,
        "domain_states_by_fixed_point": {k: r.domain_states for k, r in results.items()},
        "controller": {"fixed_point": main_key, "form": "layered" if main.layers else "explicit",
                       "nodes": controller.nodes, "files": files.get("controller", [])},
        "synthesis": syn_report,
        "closed_loop": closed,
        "figures": figures,
        "stage_seconds": seconds,
    }
