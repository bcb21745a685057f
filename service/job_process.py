"""The process one job runs in: ``python -m service.job_process JOB_ID``, started by :mod:`service.supervisor`.

It reads its settings from stdin (a JSON object: ``settings`` without the token, ``scheduler``, ``parent``), runs
:func:`workers.job.run_job` on the job's spec from the job store, and writes the job's progress events and its
outcome (``succeeded``, or ``failed`` with the reason) to the store. It writes nothing when it is stopped: on
``SIGTERM`` the next progress event raises :class:`~workers.job.JobCancelled`, the job unwinds (its cluster tasks
cancelled, the audit's child stopped) and the process exits with :data:`~service.supervisor.EXIT_STOPPED`; the
supervisor records why it stopped the job (cancelled, over its time limit, the API stopping).

It dies with its parent, the API (``PR_SET_PDEATHSIG``): a job whose API is gone is re-queued by the next API, so
it must not run on beside it. Should the machine run out of memory before the supervisor sees a job over its memory
limit, the kernel kills a job process, never the API: each job process, and every process it starts, has the
largest ``oom_score_adj``.
"""

from __future__ import annotations

import ctypes
import json
import logging
import os
import signal
import sys
import threading
import time
from typing import Any

log = logging.getLogger("compabs.job")

#: Seconds between stored progress events of one stage (a stage's first and last event are always stored).
PROGRESS_INTERVAL = 0.25
_STOP = threading.Event()
#: Linux's prctl option: the signal this process gets when its parent dies.
_PR_SET_PDEATHSIG = 1


def _die_with_parent(parent: int) -> None:
    """Be killed when the API dies (Linux); elsewhere, or if that fails, a thread that watches the parent."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl")
    except (OSError, AttributeError):
        def watch() -> None:
            while os.getppid() == parent:
                time.sleep(1.0)
            os.killpg(0, signal.SIGKILL)

        threading.Thread(target=watch, name="parent-watch", daemon=True).start()
    if os.getppid() != parent:  # the parent died before the request above took effect
        os._exit(EXIT_ORPHANED)


#: The OOM killer's bias for a job's processes (inherited by its children): the largest, the first to go.
OOM_SCORE_ADJ = 1000


def _first_to_go_when_out_of_memory() -> None:
    # Raising one's own score needs no privilege; where /proc has no such file (not Linux) nothing is changed.
    try:
        with open("/proc/self/oom_score_adj", "w") as fh:
            fh.write(str(OOM_SCORE_ADJ))
    except OSError:
        pass


#: Exit status of a job process whose API was already gone when it started.
EXIT_ORPHANED = 70


def _on_term(signum: int, frame: Any) -> None:
    _STOP.set()


def _progress(store: Any, job_id: str):
    from workers.job import JobCancelled

    last: dict[str, float] = {}

    def progress(stage: str, done: int, total: int, message: str) -> None:
        if _STOP.is_set():
            raise JobCancelled("stopped by the API")
        now = time.monotonic()
        if stage not in last or done <= 0 or done >= total or now - last[stage] >= PROGRESS_INTERVAL:
            last[stage] = now
            store.add_progress(job_id, stage, done, total, message)

    return progress


def run(job_id: str, settings: Any, store: Any, scheduler: str | None) -> int:
    """Run the job ``job_id`` and record its outcome; the process's exit status."""
    from pipelines.errors import CompabsError
    from pipelines.spec.model import parse_spec
    from pipelines.spec.validate import cap_synthesis_processes
    from service.job_store import JobStatus
    from service.models import summarize
    from service.supervisor import EXIT_STOPPED, end_job
    from workers.executors import Execution
    from workers.job import JobCancelled, run_job
    from workers.stages import JobPolicy

    rec = store.get(job_id)
    if rec is None or rec.status != JobStatus.RUNNING or rec.cancel_requested:
        return EXIT_STOPPED
    try:
        # Local synthesis helpers at most one per core (a spec may ask for 64).
        spec = cap_synthesis_processes(parse_spec(json.loads(rec.spec)), on_cluster=scheduler is not None)
        report = run_job(
            spec, settings.jobs_dir / job_id, execution=Execution(scheduler=scheduler, in_process=scheduler is None),
            progress=_progress(store, job_id), policy=JobPolicy(allowed_modules=tuple(settings.allowed_modules), caps=settings.caps()),
        )
    except JobCancelled:
        return EXIT_STOPPED
    except Exception as exc:
        if _STOP.is_set():  # failing because it is being stopped (its cluster connection closing, say)
            return EXIT_STOPPED
        if isinstance(exc, CompabsError):
            end_job(store, settings, job_id, JobStatus.FAILED, error=str(exc))
        else:
            log.exception("job %s failed with an internal error", job_id)
            end_job(store, settings, job_id, JobStatus.FAILED,
                    error=f"internal error ({type(exc).__name__}: {exc}); the server log has the details. "
                    "Please report it with the spec.")
        return 0
    summary = summarize(report)
    closed = report.get("closed_loop") or {}
    error = None
    if summary["audit_violations"]:
        error = (f"the audit found {summary['audit_violations']} concrete transitions missing from the abstraction "
                 "(a soundness bug); report.json in the job's directory has the details")
    elif closed.get("violations"):
        error = f"{closed['violations']} closed-loop runs violated the specification: {closed.get('first_violation')}"
    if error:
        end_job(store, settings, job_id, JobStatus.FAILED, error=error, summary=summary, figures=[])
    else:
        end_job(store, settings, job_id, JobStatus.SUCCEEDED, summary=summary, figures=list(report.get("figures", [])))
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: python -m service.job_process JOB_ID (settings as JSON on stdin)", file=sys.stderr)
        return 2
    payload = json.loads(sys.stdin.read())
    _die_with_parent(int(payload["parent"]))
    _first_to_go_when_out_of_memory()
    signal.signal(signal.SIGTERM, _on_term)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C at the API's terminal is the API's to handle
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    log.setLevel(logging.INFO)

    from service.manager import new_store
    from service.settings import Settings

    settings = Settings.model_validate(payload["settings"])
    store = new_store(settings)
    try:
        return run(argv[0], settings, store, payload.get("scheduler"))
    finally:
        store.close()


if __name__ == "__main__":
    code = main()
    # Everything the job owes the API is in the job store. Skipping the interpreter's teardown keeps its collector
    # from clearing CUDD functions held in reference cycles after their manager (dd then prints "Still N nodes
    # referenced upon shutdown" into the job's log on runs that went well).
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
