"""The stages of a job, defined once (ARCHITECTURE "The job, as data flowing through").

``run_abstraction`` takes a spec through plan -> Lipschitz constants -> subsystem abstractions (Algorithm 1)
-> interconnection abstraction (Algorithms 2-3) -> audit, and returns the artefacts and the report. How the
per-chunk tasks run is a parameter: ``mapper(fn, args_list)`` returns the results of ``fn(*args)`` for each
argument tuple, in-process by default; the distributed runner passes one backed by a Dask client.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from .audit import AuditResult, audit_interconnection, audit_subsystem
from .errors import LipschitzError
from .lipschitz import estimate_lipschitz
from .network import Network, Subsystem, build_network
from .region import AbstractRegion, abstract_region
from .spec import JobSpec, spec_hash
from .subsystem import SLOPE_RTOL, CellsResult, SubsystemRelation, abstract_cells, assemble, chunk_ranges

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
) -> tuple[SubsystemRelation, dict]:
    """Abstract one (group of identical) subsystem(s), validating the Lipschitz constants on its data."""
    spec = sub.spec
    chunks = chunk_ranges(sub, chunk_cells)
    for attempt in range(2):
        L_x, L_w = constants["x"].value, constants["w"].value
        args = [(sub, a, b, L_x, L_w, spec.growth_bound, spec.scp_objective) for a, b in chunks]
        results: list[CellsResult] = []
        for i, r in enumerate(mapper(abstract_cells, args)):
            results.append(r)
            progress("subsystems", done_before + i + 1, total, f"{sub.name}: chunk {i + 1}/{len(chunks)}")
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
                raise LipschitzError(
                    f"subsystem {names}: the given L_{arg} = {c.value:g} is contradicted by the data: slope "
                    f"{rec.slope:.6g} observed at {where}. An abstraction built with it would be unsound. Give "
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


def run_abstraction(
    spec: JobSpec,
    *,
    mapper: Mapper = local_mapper,
    progress: Progress = _no_progress,
    allowed_modules: Sequence[str] | None = None,
    audit: bool = True,
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

    Raises
    ------
    CompabsError
        Subclasses name what is wrong: SpecError, ExpressionError, BlackBoxError, LipschitzError,
        CertificationError.
    """
    from .interconnection import abstract_interconnection

    rng = np.random.default_rng(spec.options.seed)
    seconds: dict[str, float] = {}

    t0 = time.perf_counter()
    progress("plan", 0, 1, "building grids")
    network = build_network(spec, allowed_modules)
    for s in network.subsystems:
        if s.triples > spec.options.max_cells:
            from .errors import SpecError

            raise SpecError(
                f"subsystem '{s.name}': {s.triples} (x, u, w) triples exceed options.max_cells = "
                f"{spec.options.max_cells}; coarsen its grids or raise the cap"
            )
    composed = network.composed_state_grid()
    spec_regions = spec.specification
    regions: dict[str, AbstractRegion] = {}
    for name in ("target", "safe", "avoid"):
        region = getattr(spec_regions, name)
        if region is not None:
            regions[name] = abstract_region(region, composed, f"specification.{name}", outer=(name == "avoid"))
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
    total_chunks = sum(len(chunk_ranges(m[0], chunk_cells)) for m in groups.values())
    done = 0
    for key, members in groups.items():
        rel, info = _abstract_one(
            members[0], members, constants[key], mapper, progress, done, total_chunks, chunk_cells
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
    if audit and spec.options.audit_transitions:
        t0 = time.perf_counter()
        n = spec.options.audit_transitions
        parts: dict[str, AuditResult] = {}
        total = len(groups) + 1
        for i, (key, members) in enumerate(groups.items()):
            parts[members[0].name] = audit_subsystem(members[0], relations[key], n, rng)
            progress("audit", i + 1, total, members[0].name)
        parts["interconnection"] = audit_interconnection(network, ia, n, rng)
        progress("audit", total, total, "interconnection")
        audit_report = {
            "transitions_checked": sum(p.transitions_checked for p in parts.values()),
            "violations": sum(p.violations for p in parts.values()),
            "parts": {k: p.as_dict() for k, p in parts.items()},
        }
        seconds["audit"] = time.perf_counter() - t0

    target = regions.get("target") or regions.get("safe")
    report = {
        "name": spec.name,
        "spec_hash": spec_hash(spec),
        "abstract_states": network.abstract_states,
        "region_states": target.states if target is not None else None,
        "regions": {k: {"states": r.states, "boxes": len(r.boxes)} for k, r in regions.items()},
        "subsystem_count": len(network.subsystems),
        "stage_seconds": seconds,
        "subsystems": infos,
        "interconnection": ia.describe(),
        "audit": audit_report,
    }
    return AbstractionResult(spec, network, relations, ia, target, report)
