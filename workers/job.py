"""The one orchestrator: the stages of a job, defined once (ARCHITECTURE "The job, as data flowing through").

``compabs run``, the REST service and ``bench/`` all call :func:`run_job` (or, for the abstraction alone,
:func:`run_abstraction`); what varies is the executor the per-cell tasks run on (:mod:`workers.executors`:
in-process or a Dask cluster), never the stages:

1. ``plan``: grids, regions and the distinct subsystems (identical ones are abstracted once);
2. ``lipschitz``: the constants, given or estimated (Algorithm 4);
3. ``subsystems``: Algorithm 1 per distinct subsystem, one :class:`~pipelines.abstraction.cells.CellTask` per
   chunk of state cells, with the constants checked against the data (docs/method.md §3);
4. ``interconnection``: Algorithms 2-3;
5. ``audit``: Theorems 4.2 and 4.7 on random concrete transitions, in this process or, while synthesis runs,
   in a child process (:mod:`workers.processes.audit_beside`);
6. ``synthesis``: the fixed points on the BDDs (Algorithm 5), the controller saved;
7. ``closed_loop``: refinement (Theorem 4.2) with the concrete black boxes, and the figures.

Every stage reports progress as ``progress(stage, done, total, message)``. Cancellation is cooperative: a
callback that raises (the service's raises :class:`JobCancelled`) unwinds the job from inside the stage; a
cluster executor then cancels the job's outstanding tasks; chunks already marked done stay in the store.
The files of the job directory are written through :mod:`workers.jobdir` only.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pipelines.abstraction.cells import CellTask
from pipelines.abstraction.lipschitz import ConstantRecord, check_constants, resolve_constant
from pipelines.abstraction.relation import CellsResult, SubsystemRelation, assemble, chunk_ranges
from pipelines.errors import CompabsError
from pipelines.network import Network, Subsystem, build_network
from pipelines.spec.model import JobSpec, spec_hash
from pipelines.spec.regions import AbstractRegion, dead_ranges, never_winning, spec_regions
from pipelines.spec.validate import Validation, check_cells, validate_spec
from pipelines.verification.audit import audit_abstraction
from workers import jobdir, resume
from workers.control import run_synthesis
from workers.errors import StoreError
from workers.executors import Execution, Executor, InProcess, OnDask
from workers.job_session import JobSession
from workers.relation_store import RelationStore
from workers.stages import STAGES, Abstraction, JobCancelled, JobPolicy, Progress, Stage, no_progress


# ====================================================================================== abstraction stages
def _abstract_subsystem(
    members: list[Subsystem], constants: dict[str, ConstantRecord], executor: Executor, chunk_cells: int | None,
    progress: Progress, done_before: int, total: int, dead: np.ndarray | None = None,
) -> tuple[SubsystemRelation, dict]:
    """Algorithm 1 for one distinct subsystem, its constants checked against its data (docs/method.md §3): a constant
    the data contradict fails the job, or is raised and the relation computed again with it. ``dead``: the cells
    not abstracted (:func:`~pipelines.spec.regions.never_winning`)."""
    sub, spec = members[0], members[0].spec
    chunks = chunk_ranges(sub, chunk_cells, executor.chunk_points)
    names = [m.name for m in members]
    for _ in range(2):
        L_x, L_w = constants["x"].value, constants["w"].value
        tasks = [CellTask(sub, a, b, L_x, L_w, spec.growth_bound, spec.scp_objective, dead_ranges(dead, a, b))
                 for a, b in chunks]
        results: list[CellsResult] = []
        for i, r in enumerate(executor.map_cells(tasks, names)):
            results.append(r)
            progress("subsystems", done_before + i + 1, total, f"{sub.name}: chunk {i + 1}/{len(chunks)}")
        # Results come in any order (a cluster: completion order); merging in cell order makes the reported
        # location of a tied largest slope independent of it.
        results.sort(key=lambda r: r.start)
        slope_x, slope_w = results[0].slope_x, results[0].slope_w
        for r in results[1:]:
            slope_x, slope_w = slope_x.merge(r.slope_x), slope_w.merge(r.slope_w)
        if check_constants(sub, ", ".join(names), constants, {"x": slope_x, "w": slope_w}):
            break
    else:  # pragma: no cover - the second pass reuses the same samples, so it cannot be violated again
        raise RuntimeError("Lipschitz constants still violated after raising them")

    rel = assemble(results, sub.state_grid.size, spec.growth_bound, L_x, L_w)
    totals: dict[str, list[int]] = {}
    for r in results:
        for name, (s, k) in r.successors.items():
            t = totals.setdefault(name, [0, 0])
            t[0] += s
            t[1] += k
    info = {
        "name": sub.name,
        "members": names,
        "growth_bound": spec.growth_bound,
        "scp_objective": spec.scp_objective,
        "triples": int(rel.blocking.size),
        "chunks": len(chunks),
        "samples_per_cell": spec.samples,
        "blocking_fraction": float(rel.blocking.mean()),
        "cells_not_abstracted": 0 if dead is None else int(dead.sum()),
        "mean_successors": {name: (s / k if k else None) for name, (s, k) in totals.items()},
        "non_blocking": {name: k for name, (s, k) in totals.items()},
        "lipschitz": {arg: c.as_dict() for arg, c in constants.items()},
    }
    return rel, info


def _plan(spec: JobSpec, validated: Validation | None, allowed_modules: Sequence[str] | None,
          progress: Progress) -> tuple[Network, dict[str, AbstractRegion], dict[str, list[Subsystem]]]:
    """The ``plan`` stage: the network, the spec's regions and the distinct subsystems (identical ones are abstracted
    once); the validation's network and regions when the caller ran it (their exact counts are not swept again),
    else built and checked here."""
    progress("plan", 0, 1, "building grids")
    if validated is not None:
        network, regions = validated.network, validated.regions
    else:
        network = build_network(spec, allowed_modules)
        check_cells(spec, network)
        regions = spec_regions(spec, network)
    groups = network.unique_subsystems()
    progress("plan", 1, 1, f"{len(network.subsystems)} subsystems, {len(groups)} distinct")
    return network, regions, groups


def _lipschitz(groups: dict[str, list[Subsystem]], rng: np.random.Generator,
               progress: Progress) -> dict[str, dict[str, ConstantRecord]]:
    """The ``lipschitz`` stage: each distinct subsystem's constants in ``x`` and ``w``, given or estimated
    (Algorithm 4), drawn from ``rng`` in the order of ``groups`` (the job's seed fixes them)."""
    constants: dict[str, dict[str, ConstantRecord]] = {}
    for i, (key, members) in enumerate(groups.items()):
        constants[key] = {arg: resolve_constant(members[0], arg, rng) for arg in ("x", "w")}
        progress("lipschitz", i + 1, len(groups), members[0].name)
    return constants


def _abstract_subsystems(
    spec: JobSpec, network: Network, regions: dict[str, AbstractRegion], groups: dict[str, list[Subsystem]],
    constants: dict[str, dict[str, ConstantRecord]], executor: Executor, progress: Progress,
) -> tuple[dict[str, SubsystemRelation], list[dict]]:
    """The ``subsystems`` stage: Algorithm 1 for each distinct subsystem (:func:`_abstract_subsystem`), one
    progress bar over all their chunks; the cells that can never win are not abstracted."""
    relations: dict[str, SubsystemRelation] = {}
    infos = []
    total = sum(len(chunk_ranges(m[0], spec.options.chunk_cells, executor.chunk_points)) for m in groups.values())
    done = 0
    for key, members in groups.items():
        rel, info = _abstract_subsystem(members, constants[key], executor, spec.options.chunk_cells, progress, done,
                                         total, never_winning(spec, network, regions))
        done += info["chunks"]
        relations[key] = rel
        infos.append(info)
    return relations, infos


def _audit_stage(
    abstraction: Abstraction, rng: np.random.Generator, progress: Progress, session: JobSession | None,
    stored: dict[str, Any] | None, resume_dir: Path | None,
) -> dict[str, Any]:
    """The ``audit`` stage (Theorems 4.2 and 4.7 on random concrete transitions): the report a first run stored
    (``stored``), or an audit started in a child process held by ``session`` (returned at once, marked
    ``pending``), or one run here and kept in ``resume_dir`` for a resumed run."""
    spec, network, relations, ia = (abstraction.spec, abstraction.network, abstraction.relations,
                                    abstraction.interconnection)
    if stored is not None:
        progress("audit", 1, 1, "read back: the first run checked these relations")
        return stored
    if session is not None:
        from workers.processes.audit_beside import BackgroundAudit

        # The child reports each part it finishes; the relay thread calls progress (the service's callback
        # writes under the job store's lock, so it may be called from that thread).
        session.pending_audit = BackgroundAudit(network, relations, ia, spec.options.audit_transitions, rng,
                                                progress=lambda done, total, part: progress("audit", done, total, part))
        progress("audit", 0, 1, "running in a child process beside synthesis")
        return {"transitions_checked": 0, "violations": 0, "pending": True}
    t0 = time.perf_counter()
    report = audit_abstraction(network, relations, ia, spec.options.audit_transitions, rng,
                               lambda done, total, part: progress("audit", done, total, part))
    abstraction.report["stage_seconds"]["audit"] = time.perf_counter() - t0
    resume.keep_audit(resume_dir, spec, report)
    return report


def _report(spec: JobSpec, network: Network, regions: dict[str, AbstractRegion], seconds: dict[str, float],
            infos: list[dict], ia: Any, read_back: bool) -> dict[str, Any]:
    """The abstraction's part of the job's report (``audit`` is filled in by the audit stage)."""
    counts = {k: r.states for k, r in regions.items()}  # exact counts cost a sweep each: once per region
    return {
        "name": spec.name,
        "spec_hash": spec_hash(spec),
        "abstract_states": network.abstract_states,
        "region_states": counts.get("target", counts.get("safe")),
        "regions": {k: {"states": counts[k], "boxes": len(r.boxes)} for k, r in regions.items()},
        "subsystem_count": len(network.subsystems),
        "stage_seconds": seconds,
        "subsystems": infos,
        "interconnection": {**ia.describe(), **({"read_back": True} if read_back else {})},
        "audit": {"transitions_checked": 0, "violations": 0},
    }


def run_abstraction(
    spec: JobSpec,
    *,
    executor: Executor | None = None,
    progress: Progress = no_progress,
    allowed_modules: Sequence[str] | None = None,
    audit: bool = True,
    session: JobSession | None = None,
    validated: Validation | None = None,
    resume_dir: Path | None = None,
) -> Abstraction:
    """Run the abstraction stages of a job (plan to audit) and build its report.

    Parameters
    ----------
    spec : JobSpec
    executor : Executor, optional
        Where the per-cell tasks run (default: this process, nothing stored).
    progress : callable
        ``progress(stage, done, total, message)``, called as work completes.
    allowed_modules
        Modules a ``module:function`` may name (``None``: any, the local command line).
    session : JobSession, optional
        Start the audit in a child process held by ``session.pending_audit`` and return without waiting: synthesis
        needs nothing the audit makes, so it runs on another core meanwhile. The caller must call
        :meth:`JobSession.finish_audit` (which fills ``report["audit"]``) or :meth:`JobSession.close`.
    validated : Validation, optional
        The spec's :func:`~pipelines.spec.validate.validate_spec`, if the caller ran it: its network and regions
        (with their exact counts) are the plan, not built and counted again.
    resume_dir : Path, optional
        The job directory: an interconnection and an audit a run of this spec stored there are read back
        (:mod:`workers.resume`).

    Raises
    ------
    CompabsError
        Subclasses name what is wrong: SpecError, ExpressionError, BlackBoxError, LipschitzError,
        CertificationError, and the executor's ClusterError, StoreError, TaskTimeoutError.
    """
    executor = executor if executor is not None else InProcess()
    rng = np.random.default_rng(spec.options.seed)
    seconds: dict[str, float] = {}

    t0 = time.perf_counter()
    network, regions, groups = _plan(spec, validated, allowed_modules, progress)
    seconds["plan"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    constants = _lipschitz(groups, rng, progress)
    seconds["lipschitz"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    relations, infos = _abstract_subsystems(spec, network, regions, groups, constants, executor, progress)
    seconds["subsystems"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    progress("interconnection", 0, 1, "sampling the map")
    ia, read_back = resume.interconnection(resume_dir, spec, network, rng)
    progress("interconnection", 1, 1, f"{len(ia.nodes)} nodes" + (", read back" if read_back else ""))
    seconds["interconnection"] = time.perf_counter() - t0

    stored = resume.stored_audit(resume_dir, spec, interconnection_read_back=read_back,
                                 chunks_computed=executor.stats.chunks_computed)
    result = Abstraction(spec, network, relations, ia, _report(spec, network, regions, seconds, infos, ia, read_back))
    if audit and spec.options.audit_transitions:
        result.report["audit"] = _audit_stage(result, rng, progress, session, stored, resume_dir)
    return result


#: Black-box evaluations of the per-cell stage below which a job that would start an embedded cluster runs in
#: process, on threads, instead (``in_process=None``): up to about a minute of work on two cores, where threads do
#: as well as two workers and starting and stopping them (3-4 s) is saved.
IN_PROCESS_EVALUATIONS = 4_000_000_000
#: Composed abstract states above which a job keeps the cluster anyway (its synthesis may run parts there).
IN_PROCESS_STATES = 10_000_000


def runs_in_process(network: Network, execution: Execution) -> bool:
    """Whether a job runs its per-cell stage in this process: as ``execution.in_process`` says, or (``None``) when
    no cluster is given and the job is small (:data:`IN_PROCESS_EVALUATIONS`, :data:`IN_PROCESS_STATES`), so a
    small job does not pay for an embedded cluster."""
    if execution.in_process is not None:
        return execution.in_process
    if execution.client is not None or execution.scheduler is not None:
        return False
    evaluations = sum(s.triples * s.spec.samples * s.spec.rhs_evaluations
                      for s in (m[0] for m in network.unique_subsystems().values()))
    return evaluations <= IN_PROCESS_EVALUATIONS and network.abstract_states <= IN_PROCESS_STATES


def _executor(spec: JobSpec, store: RelationStore, execution: Execution, in_process: bool) -> tuple[Executor, Any]:
    """The executor a job asks for, and the cluster connection to close afterwards (or ``None``)."""
    if in_process:
        return InProcess(store, threads=execution.workers), None
    from workers.cluster import client_info, connect

    if execution.client is not None:
        return OnDask(execution.client, store, client_info(execution.client), spec.options.task_timeout), None
    conn = connect(execution.scheduler, execution.workers)
    client, info = conn
    return OnDask(client, store, info, spec.options.task_timeout), conn


def abstract_job(
    spec: JobSpec,
    out_dir: str | os.PathLike[str],
    execution: Execution | None = None,
    *,
    progress: Progress = no_progress,
    policy: JobPolicy | None = None,
    audit: bool = True,
    overwrite: bool = False,
    session: JobSession | None = None,
) -> tuple[Abstraction, dict[str, Any]]:
    """The abstraction stages of a job whose relations go into its directory's store (resumable).

    ``out_dir`` is the job directory or an fsspec URL; its relation store is ``out_dir/relations.zarr`` and chunks
    marked done there by an earlier run of the same spec are reused. The per-cell tasks run where ``execution``
    says (:class:`~workers.executors.Execution`; default: an embedded cluster of two workers).

    Returns the abstraction and the report's ``runner`` section (``scheduler``, ``workers``, ``dashboard``,
    ``embedded``, ``store``, chunk counts, ``task_compute_seconds``). With a ``session`` (a job that goes on to
    synthesis) the audit starts in a child process beside synthesis (:meth:`JobSession.finish_audit`), and the
    session holds the cluster's client, left open for synthesis, and the connection this call opened: the caller
    must call :meth:`JobSession.close` (a cluster this call started closes then; a caller's client stays open).

    Before anything else the spec is validated (:func:`pipelines.spec.validate.validate_spec`, with ``policy``'s
    allowed modules and caps) and a local directory claimed (:func:`workers.jobdir.claim`: created if needed, writable, not
    another spec's); a directory this call created is removed again if the call fails before storing anything.

    Raises
    ------
    CompabsError
        As :func:`run_abstraction` and :func:`~pipelines.spec.validate.validate_spec`;
        :class:`~workers.errors.StoreMismatchError` for a store or job files of another spec (unless ``overwrite``),
        :class:`~workers.errors.StoreError` for a directory that cannot be written,
        :class:`~workers.errors.ClusterError` when the cluster cannot be reached.
    """
    # Check the spec, claim the directory and open the store before starting a cluster: a bad spec, a directory
    # that cannot be written or holds another job, or a stale store fails at once, and leaves no new directory.
    execution = execution if execution is not None else Execution()
    policy = policy if policy is not None else JobPolicy()
    validated = validate_spec(spec, allowed_modules=policy.allowed_modules, caps=policy.caps)
    network = validated.network
    in_process = runs_in_process(network, execution)
    local = "://" not in os.fspath(out_dir)
    created = None
    if local:
        out_dir, created = jobdir.claim(out_dir, spec, overwrite=overwrite)
    try:
        store = RelationStore.open(jobdir.relations_url(out_dir), spec, network, overwrite=overwrite)
        executor, conn = _executor(spec, store, execution, in_process)
        kept = False
        try:
            result = run_abstraction(spec, executor=executor, progress=progress,
                                     allowed_modules=policy.allowed_modules, audit=audit, session=session,
                                     validated=validated,
                                     resume_dir=Path(out_dir) if local else None)
            try:
                store.consolidate()
                if local:  # what `compabs audit` checks
                    jobdir.save_interconnection(result.interconnection, out_dir, spec)
            except OSError as exc:
                if session is not None:  # nothing will wait for it: the caller gets no abstraction
                    session.cancel_audit()
                raise StoreError(
                    f"writing the job's files in {os.fspath(out_dir)} failed: {exc}. Every chunk is stored; free space "
                    "or fix the permissions and run the job again to finish it."
                ) from None
            except BaseException:
                if session is not None:
                    session.cancel_audit()
                raise
            if session is not None and not in_process:
                session.client = execution.client if conn is None else conn.client
                session.connection, kept = conn, True
        finally:
            if conn is not None and not kept:
                conn.close()
    except BaseException:
        if created is not None:  # a directory this run made and stored nothing in is not left behind
            jobdir.discard_unused(created)
        raise
    runner = {**executor.describe(), "store": store.url, **executor.stats.as_dict()}
    return result, runner


# ====================================================================================== the whole job
def run_job(
    spec: JobSpec,
    out_dir: str | os.PathLike[str],
    execution: Execution | None = None,
    *,
    progress: Progress | None = None,
    policy: JobPolicy | None = None,
    audit: bool = True,
    synthesis: bool = True,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Run every stage of a job and write its files into ``out_dir`` (:mod:`workers.jobdir`).

    Parameters
    ----------
    spec : JobSpec
    out_dir : str or path
        The job's directory: created, or one of an earlier run of the same spec (its stored chunks are reused);
        refused if it cannot be written or holds another spec's job (before any work).
    execution : Execution, optional
        Where the per-cell tasks (and the synthesis' parts) run (:class:`~workers.executors.Execution`; default: an
        embedded cluster of two workers).
    progress : callable, optional
        ``progress(stage, done, total, message)``; raising from it (e.g. :class:`JobCancelled`) stops the job and
        cancels its outstanding cluster tasks.
    policy : JobPolicy, optional
        What the caller allows (:class:`~workers.stages.JobPolicy`): the modules a ``module:function`` black box may
        come from and the cost model's caps the spec is validated against before anything starts (default: any
        module and the command line's caps, as on the local command line; the service passes its own).
    audit, synthesis : bool
        Run the audit; synthesize a controller, run the closed loop and draw the figures (if
        ``spec.options.synthesis`` too).
    overwrite : bool
        Replace the relation store and job files of another spec in ``out_dir`` instead of refusing.

    Returns
    -------
    dict
        The report, as written to ``out_dir/report.json``.

    Raises
    ------
    CompabsError
        Any error a user can cause or fix, naming the field, cell or token.
    JobCancelled
        Or whatever else ``progress`` raised.
    """
    progress = progress or no_progress
    synthesize = bool(spec.options.synthesis and synthesis)
    # The spec is validated and the directory claimed (created) first, in abstract_job. With synthesis to run,
    # the audit runs beside it in a child process: it needs nothing synthesis makes, and its violations set the
    # job's status at the end either way.
    # The cluster stays up through synthesis: the fixed points' parts run on its workers (workers.dask_cpre).
    # Leaving the session stops the audit's child on an error or a cancellation (nothing when it finished) and
    # closes a cluster this job started.
    with JobSession() as session:
        result, runner = abstract_job(spec, Path(out_dir), execution, progress=progress, policy=policy, audit=audit,
                                      overwrite=overwrite, session=session if synthesize else None)
        out = Path(out_dir)
        result.report["runner"] = runner
        if synthesize:
            extra = run_synthesis(result, out, progress=progress, client=session.client)
            result.report["stage_seconds"].update(extra.pop("stage_seconds"))
            result.report.update(extra)
        session.finish_audit(result, progress)
        resume.keep_audit(out, spec, result.report["audit"])
    try:
        jobdir.write_spec(out, spec)
        jobdir.write_report(out, result.report)  # last: a report on disk means the job's files are complete
    except OSError as exc:  # a full or read-only disk: say which file, keep what was written
        raise CompabsError(f"cannot write the job's files in {out}: {exc.strerror or exc} ({exc.filename or ''}); "
                           "free space or fix permissions and run the job again (stored chunks are reused)") from None
    return result.report


__all__ = ["STAGES", "Abstraction", "Execution", "JobCancelled", "JobPolicy", "JobSession", "Progress", "Stage",
           "abstract_job", "run_abstraction", "run_job"]
