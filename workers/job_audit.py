"""``compabs audit DIR``: re-check a finished job's stored abstraction and controller against the black boxes.

Always against what the job *stored* (:func:`workers.jobdir.load_job`: ``relations.zarr``,
``interconnection.npz``, the controller files), never a recomputed abstraction:

* the parts the job's own audit stage checks (:func:`pipelines.verification.audit.audit_abstraction`): every
  distinct subsystem, the interconnection and the composition, ``N`` random concrete transitions each, a share of
  them on cell boundaries and box edges;
* the integrity of the stored relations: every chunk against the checksum in its done-marker (a damaged
  chunk, missing, unreadable or not matching, is one violation, named by group and chunk);
* the controller, if the job has one: closed-loop runs of the concrete system under it from random states of its
  domain and from the spec's initial states inside it (:func:`pipelines.verification.closed_loop.run_closed_loop`;
  an ``ltl`` job's controller with memory tracks the automaton state and each run must accept within its bound,
  :func:`pipelines.verification.product_loop.run_product_loop`).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from pipelines.array_controller import ArrayController
from pipelines.controller import Controller
from pipelines.controller_loading import load_controller
from pipelines.errors import CompabsError
from pipelines.product_controller import ProductController
from pipelines.spec.costs import Caps, CostError, audit_evaluations
from pipelines.spec.model import spec_hash
from pipelines.spec.regions import closed_loop_regions, spec_regions
from pipelines.verification.audit import audit_abstraction
from pipelines.verification.closed_loop import run_closed_loop
from pipelines.verification.product_loop import run_product_loop
from workers import jobdir

#: ``progress(part, done, total)`` for long audits.
AuditProgress = Callable[[str, int, int], None]


def _controller(arts: jobdir.JobArtifacts) -> Controller | ArrayController | ProductController | None:
    """The job's stored controller (``None`` without one), verified against its checksums and the job's spec hash
    before any file of it is read (:func:`pipelines.controller_loading.load_controller`)."""
    if not arts.has_controller:
        recorded = (arts.report.get("controller") or {}).get("files") if isinstance(arts.report, dict) else None
        if recorded:  # the report says synthesis saved one: its absence is damage, not a job without synthesis
            raise jobdir.ArtifactError(f"{arts.directory}/{jobdir.CONTROLLER}.json is missing, but the job's "
                                       f"report records a controller ({', '.join(map(str, recorded))}); run the "
                                       "job again")
        return None
    controller = load_controller(arts.directory, jobdir.CONTROLLER, job_hash=spec_hash(arts.spec))
    if not isinstance(controller, Controller | ArrayController | ProductController):  # pragma: no cover - load_controller reads a job's
        raise CompabsError(f"{arts.directory}/{jobdir.CONTROLLER}.json is not a synthesized controller")
    return controller


def _closed_loop(arts: jobdir.JobArtifacts, controller: Controller | ArrayController | ProductController, runs: int,
                 rng: np.random.Generator) -> dict[str, Any]:
    """Closed-loop runs of the concrete system under the job's stored controller."""
    spec, network = arts.spec, arts.network
    if isinstance(controller, ProductController):
        t0 = time.perf_counter()
        product = run_product_loop(network, controller, spec.options.initial_states, runs,
                                   spec.options.closed_loop_steps, rng)
        random_runs = sum(1 for origin, _, _ in product.runs if origin == "random")
        return {"runs": len(product.runs), "violations": product.violations,
                "first_violation": product.first_violation, "steps": product.steps, "form": "product",
                "accepted": product.accepted, "domain_empty": random_runs == 0 and runs > 0,
                "seconds": time.perf_counter() - t0}
    checked = closed_loop_regions(spec, network, spec_regions(spec, network))
    steps = (arts.report.get("closed_loop") or {}).get("steps") or spec.options.closed_loop_steps or 60
    t0 = time.perf_counter()
    # the controller draws one admissible input at random, as the job's closed loop does: listing them all first is
    # the same draw, but a network of permissive subsystem controllers admits millions of joint inputs per state
    loop = run_closed_loop(network, controller, spec.options.initial_states, runs, int(steps), rng,
                           spec.specification.kind, checked["target"], checked["avoid"], safe=checked["safe"])
    random_runs = sum(1 for origin, _, _ in loop.runs if origin == "random")
    return {
        "runs": len(loop.runs),
        "violations": loop.violations,
        "first_violation": loop.first_violation,
        "steps": int(steps),
        "form": controller.meta.get("form", "explicit"),
        "domain_empty": random_runs == 0 and runs > 0,
        "seconds": time.perf_counter() - t0,
    }


def _relation_store(arts: jobdir.JobArtifacts) -> dict[str, Any]:
    """The integrity of the stored relations: every chunk checked against its checksum (``load_job`` did)."""
    damaged = arts.damaged_chunks
    first = None
    if damaged:
        more = f" ({len(damaged) - 1} more damaged chunks in {jobdir.AUDIT})" if len(damaged) > 1 else ""
        first = (f"damaged relation chunk: {damaged[0]['message']}{more}. Run the job again into {arts.directory} "
                 "(same spec) to recompute the damaged chunks")
    return {"chunks_checked": arts.chunks_checked, "damaged": damaged, "first_damaged": first}


def _transitions_per_part(arts: jobdir.JobArtifacts, transitions: int | None, caps: Caps) -> int:
    """The transitions each part draws: as asked, else the spec's ``audit_transitions`` (10^6 if 0), refused when
    negative or when every part drawing them (the composition too, not the job audit's tenth) would pass the cost
    model's ``max_audit_evaluations``, before the long part starts."""
    if transitions is None:
        transitions = arts.spec.options.audit_transitions or 1_000_000
    if transitions < 0:
        raise CompabsError(f"--transitions must be >= 0, got {transitions}")
    evaluations = audit_evaluations(transitions, len(arts.network.unique_subsystems()), len(arts.network.subsystems),
                                    composition=transitions)
    if evaluations > caps.max_audit_evaluations:
        raise CostError("--transitions", evaluations, caps.max_audit_evaluations, "max_audit_evaluations",
                        f"--transitions {transitions:,} makes {evaluations:,} black-box evaluations; {caps.owner} cap "
                        f"max_audit_evaluations is {caps.max_audit_evaluations:,}: give fewer transitions")
    return transitions


def _fresh_seed() -> int:
    """A seed drawn from fresh entropy, reported in the result so the audit can be repeated."""
    entropy = np.random.SeedSequence().entropy
    assert isinstance(entropy, int)  # drawn fresh (an int) when none is given
    return int(entropy % (2**63))


def _audited_parts(arts: jobdir.JobArtifacts, transitions: int, rng: np.random.Generator,
                   report: AuditProgress) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    """Theorems 4.2 and 4.7 on random concrete transitions (:func:`~pipelines.verification.audit.audit_abstraction`)
    and its report per part: each distinct subsystem (with its members and the file it is stored in), the
    interconnection and the composition, each with its time."""
    ia = arts.interconnection
    assert ia is not None  # load_job reads it (or raises ArtifactError)
    seconds: dict[str, float] = {}
    audited = audit_abstraction(arts.network, arts.relations, ia, transitions, rng,
                                lambda done, total, part: report(part, done, total + 1), composition=transitions,
                                seconds=seconds)
    parts = {}
    for key, members in arts.network.unique_subsystems().items():
        parts[f"subsystem {members[0].name}"] = {**audited["parts"][members[0].name],
                                                 "seconds": seconds[members[0].name],
                                                 "members": [m.name for m in members],
                                                 "stored_as": arts.relation_files.get(key)}
    parts["interconnection"] = {**audited["parts"]["interconnection"], "mode": ia.mode,
                                "seconds": seconds["interconnection"]}
    parts["composition"] = {**audited["parts"]["composition"], "seconds": seconds["composition"]}
    return audited, parts


def audit_job(
    directory: str | os.PathLike[str],
    transitions: int | None = None,
    seed: int | None = None,
    runs: int = 20,
    *,
    allowed_modules: Sequence[str] | None = None,
    progress: AuditProgress | None = None,
    write: bool = True,
    caps: Caps | None = None,
) -> dict[str, Any]:
    """Audit a finished job's stored abstraction and controller; write ``DIR/audit.json``.

    Parameters
    ----------
    directory : path
        The job's directory (``compabs run --out``, or the service's ``DATA/jobs/<id>``).
    transitions : int, optional
        Random concrete transitions per part (each distinct subsystem, the interconnection, the composition).
        Default: the spec's ``options.audit_transitions``, or 10^6 if that is 0.
    seed : int, optional
        Seed of the random draws (default: fresh entropy; the seed used is in the result).
    runs : int
        Closed-loop runs from random domain states (0: none; the spec's initial states in the domain are always
        run).
    allowed_modules : sequence of str, optional
        Modules a ``module:function`` black box may come from (``None``: any, as on the local command line).
    progress : callable, optional
        ``progress(part, done, total)``.
    write : bool
        Write ``DIR/audit.json``.
    caps : Caps, optional
        The cost model's caps; ``transitions`` is bounded by ``max_audit_evaluations`` (default:
        :meth:`~pipelines.spec.costs.Caps.local`).

    Returns
    -------
    dict
        ``transitions_checked``, ``violations`` (transitions, damaged relation chunks and closed-loop runs),
        ``parts`` (per part: ``transitions_checked``, ``violations``, ``skipped_blocking``, ``first_violation``;
        a part ``relation store`` only when chunks are damaged, one violation each, naming group and chunk),
        ``relation_store`` (``chunks_checked``, ``damaged``: the chunks missing, unreadable or not matching their
        checksums, ``first_damaged``), ``closed_loop`` (or ``None`` without a controller), ``seed``,
        ``relation_source``, ``relation_files``.

    Raises
    ------
    CompabsError
        A missing or damaged file (:class:`workers.jobdir.ArtifactError`; for a controller file, damaged,
        replaced or of another spec: :class:`~pipelines.controller_integrity.ControllerIntegrityError`), or a
        spec that no longer builds.
    """
    report = progress or (lambda *_: None)
    arts = jobdir.load_job(directory, allowed_modules)
    controller = _controller(arts)  # a damaged or foreign controller is refused before the long part
    transitions = _transitions_per_part(arts, transitions, caps if caps is not None else Caps.local())
    seed = _fresh_seed() if seed is None else seed
    rng = np.random.default_rng(seed)
    audited, parts = _audited_parts(arts, transitions, rng, report)
    store = _relation_store(arts)
    if store["damaged"]:
        parts["relation store"] = {
            "transitions_checked": 0, "violations": len(store["damaged"]), "skipped_blocking": 0,
            "first_violation": store["first_damaged"], "chunks_checked": store["chunks_checked"],
            "damaged_chunks": store["damaged"], "seconds": 0.0,
        }
    closed = _closed_loop(arts, controller, runs, rng) if controller is not None else None
    last = len(arts.network.unique_subsystems()) + 3
    report("closed loop", last, last)
    result = {
        "directory": str(arts.directory),
        "job": arts.spec.name,
        "seed": seed,
        "transitions_per_part": transitions,
        "relation_source": arts.relation_source,
        "relation_files": arts.relation_files,
        "transitions_checked": audited["transitions_checked"],
        "transition_violations": audited["violations"],
        "violations": audited["violations"] + len(store["damaged"]) + (closed["violations"] if closed else 0),
        "relation_store": store,
        "parts": parts,
        "closed_loop": closed,
    }
    if write:
        jobdir.write_audit(arts.directory, result)
    return result
