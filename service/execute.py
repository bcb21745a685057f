"""Running one job end to end: the abstraction (on a Dask cluster or in-process), synthesis, the files.

:func:`execute_job` is the one body shared by ``compabs run`` and the REST service, so the two cannot drift:
both write the same ``spec.json``, ``report.json``, controller files and figures into the job's directory.

Cancellation is cooperative: the ``progress`` callback is called by every stage as work completes, and a
callback that raises (the service's raises :class:`JobCancelled` once a cancel flag is set) unwinds the job
from inside the stage. On a cluster the runner's :class:`workers.runner.StoreMapper` then cancels the job's
outstanding Dask tasks (its generator's ``finally``); chunks already marked done stay in the relation store.
A stage that calls ``progress`` rarely (the interconnection, one subsystem's audit, synthesis) is cancelled
when it next reports.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from pipelines.errors import CompabsError, SpecError

if TYPE_CHECKING:  # the CLI imports this module; keep its start-up free of pydantic models it may not need
    from pipelines.spec.model import JobSpec

#: ``progress(stage, done, total, message)``, as for :func:`workers.job.run_abstraction`.
Progress = Callable[[str, int, int, str], None]

#: The stages in the order a job runs them (the order of progress bars and of the API's ``stages``).
STAGES = ("plan", "lipschitz", "subsystems", "interconnection", "audit", "synthesis", "closed_loop")


class JobCancelled(Exception):
    """Raised by a progress callback to stop a job; deliberately not a ``CompabsError`` (not a user error).

    Parameters
    ----------
    reason : str
        Why the job stopped (recorded by the service).
    """

    def __init__(self, reason: str = "cancelled") -> None:
        super().__init__(reason)
        self.reason = reason


def _no_progress(stage: str, done: int, total: int, message: str) -> None:
    pass


def json_default(o: Any) -> Any:
    """``json.dumps`` fallback for numpy scalars and arrays in reports."""
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def save_relations(result: Any, out: Path) -> None:
    """Write each distinct subsystem relation as ``relations/<key>.npz`` (lo, hi, blocking)."""
    rel_dir = out / "relations"
    rel_dir.mkdir(parents=True, exist_ok=True)
    for key, rel in result.relations.items():
        np.savez_compressed(rel_dir / f"{key}.npz", lo=rel.lo, hi=rel.hi, blocking=rel.blocking)


def execute_job(
    spec: JobSpec,
    out_dir: str | os.PathLike[str],
    *,
    client: Any = None,
    scheduler: str | None = None,
    workers: int = 2,
    in_process: bool = False,
    progress: Progress | None = None,
    allowed_modules: Sequence[str] | None = None,
    audit: bool = True,
    synthesis: bool = True,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Run a job's stages and write its files into ``out_dir``.

    Parameters
    ----------
    spec : JobSpec
    out_dir : str or path
        The job's directory (created): ``relations.zarr`` (cluster) or ``relations/`` (in-process),
        ``spec.json``, ``report.json``, the controller files and the figures. Chunks already in its relation
        store from an earlier run of the same spec are reused (resume).
    client : distributed.Client, optional
        A long-lived client to run the per-cell stage on (not closed); otherwise one is connected per job.
    scheduler : str, optional
        ``tcp://HOST:PORT`` when no ``client`` is given (``None``: ``COMPABS_SCHEDULER`` or an embedded
        cluster of ``workers`` processes).
    workers : int
        Worker processes of an embedded cluster.
    in_process : bool
        Run the per-cell stage in this process, without Dask (``client`` and ``scheduler`` are ignored).
    progress : callable, optional
        ``progress(stage, done, total, message)``; raising from it (e.g. :class:`JobCancelled`) stops the
        job and cancels its outstanding cluster tasks.
    allowed_modules : sequence of str, optional
        Modules a ``module:function`` black box may come from (``None``: any, as on the local command line;
        ``()``: none).
    audit : bool
        Run the audit.
    synthesis : bool
        Synthesize a controller, run the closed loop and draw the figures (if ``spec.options.synthesis``).
    overwrite : bool
        Replace a relation store of another spec in ``out_dir`` instead of refusing.

    Returns
    -------
    dict
        The report, as written to ``out_dir/report.json``.

    Raises
    ------
    CompabsError
        Any error a user can cause or fix, naming the field, cell or token (``SpecError`` when ``out_dir``
        cannot be created).
    JobCancelled
        Or whatever else ``progress`` raised.
    """
    from workers.job import run_abstraction

    progress = progress or _no_progress
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SpecError(f"--out {out}: cannot create the directory: {exc.strerror}") from None
    synthesize = bool(spec.options.synthesis and synthesis)
    # With synthesis to run, the audit runs beside it in a child process (workers.processes.audit_beside): it needs
    # nothing synthesis makes, and its violations set the job's status at the end either way.
    if in_process:
        result = run_abstraction(spec, progress=progress, allowed_modules=allowed_modules, audit=audit,
                                 audit_beside=synthesize)
    else:
        from workers.runner import run_job

        result, runner = run_job(
            spec, out, scheduler=scheduler, workers=workers, progress=progress, allowed_modules=allowed_modules,
            audit=audit, overwrite=overwrite, client=client, audit_beside=synthesize,
        )
        result.report["runner"] = runner
    try:
        if synthesize:
            from workers.job import run_synthesis

            extra = run_synthesis(result, out, progress=progress)
            result.report["stage_seconds"].update(extra.pop("stage_seconds"))
            result.report.update(extra)
        result.finish_audit(progress)
    finally:
        result.cancel_audit()  # an error or a cancellation: stop the child (nothing when finished)
    try:
        if in_process:
            from workers.jobdir import save_interconnection

            save_relations(result, out)
            save_interconnection(result.interconnection, out, spec)  # what `compabs audit` checks (runner does its own)
        (out / "spec.json").write_text(json.dumps(spec.model_dump(mode="json"), indent=1))
        # Written last (through a temporary and a rename): a report on disk means the job's files are complete.
        tmp = out / "report.json.partial"
        tmp.write_text(json.dumps(result.report, indent=2, default=json_default))
        tmp.replace(out / "report.json")
    except OSError as exc:  # a full or read-only disk: say which file, keep what was written
        raise CompabsError(f"cannot write the job's files in {out}: {exc.strerror or exc} ({exc.filename or ''}); "
                           "free space or fix permissions and run the job again (stored chunks are reused)") from None
    return result.report
