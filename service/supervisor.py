"""Each running job in its own process tree, started, watched and stopped by the API (:mod:`service.manager`).

A job runs as ``python -m service.job_process JOB_ID`` (:mod:`service.job_process`), a child of the API in a
session of its own, so that its process group holds everything it starts (the audit beside synthesis, the
synthesis helpers, a black box's own processes): the API's process never computes, and stopping a job signals
the whole group. The child gets its settings on stdin (never the token) and speaks to the API only through the
job store: it writes its progress events and its outcome there, the API reads them from there.

Stopping (:meth:`JobProcess.stop`): ``SIGTERM`` to the group, which the job process turns into
:class:`~workers.job.JobCancelled` at its next progress event (its cluster tasks cancelled, its helpers stopped);
whatever is left after ``grace`` seconds (a process inside one long CUDD call does not see the signal) gets
``SIGKILL``. A job process also dies with the API (``PR_SET_PDEATHSIG`` on Linux), and each start writes a pid
file (``DATA/run/<id>.pid``) so that an API started after a crash kills a job process that outlived it before the
job is resumed (:func:`kill_orphans`).

Memory (:meth:`JobProcess.memory_over`): the supervisor sums the resident memory of the job's process group at
each look, and, only when that sum is over the job's limit, the proportional set sizes (``/proc/PID/smaps_rollup``:
a page shared by several processes, the interpreter's libraries say, counted once in all); over the limit by that
measure, the group is killed. Resident sizes alone would count each helper's copy of the shared libraries (tens of
MB a process) again. A per-process ``RLIMIT_AS`` is not used: it bounds address space, not memory (a job process
maps gigabytes it never touches: thread stacks, malloc arenas, CUDD's and numba's reservations), it bounds each
process and not the tree, and where it bites, inside CUDD or numpy, it turns into a failed allocation that may
crash the process with no reason recorded. The kernel's OOM killer remains the backstop for a burst faster than
the supervisor's look: the job process raises its own ``oom_score_adj`` (:mod:`service.job_process`), so a job,
never the API, is what the kernel kills.

Its output (Dask's, a black box's prints, a traceback) goes to ``DATA/logs/<id>.log``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import psutil

from service.job_store import JobStatus, JobStore
from service.settings import Settings
from workers import checkpoint_store, jobdir
from workers.processes.children import PACKAGE_ROOT

log = logging.getLogger("compabs.service")

#: The job process's exit status when it stopped on ``SIGTERM`` (a cancel, a time limit or the API stopping):
#: it recorded no outcome; the supervisor does (EX_TEMPFAIL).
EXIT_STOPPED = 75
#: The module the job process runs.
JOB_MODULE = "service.job_process"


def end_job(store: JobStore, settings: Settings, job_id: str, status: JobStatus, **fields: Any) -> Any:
    """End a job ``cancelled`` or ``failed`` (or ``succeeded``); a job that does not succeed loses its synthesis
    checkpoints (:func:`workers.checkpoint_store.remove`: such a job is never resumed, and a large case's iterates
    take hundreds of MB). Its other files stay. Returns the record (``None``: no such job)."""
    if status != JobStatus.SUCCEEDED:
        checkpoint_store.remove(settings.jobs_dir / job_id / jobdir.CHECKPOINTS)
    return store.set_status(job_id, status, **fields)


def _start_time(pid: int) -> str | None:
    """The kernel's start time of ``pid`` (``/proc/PID/stat`` field 22), ``None`` if it is not running (or not on
    Linux): with the pid, it names one process (pids are reused)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rpartition(")")[2].split()[19]


def _signal_group(pgid: int, sig: int) -> bool:
    try:
        os.killpg(pgid, sig)
        return True
    except (ProcessLookupError, PermissionError):
        return False


def group_members(pgid: int) -> list[psutil.Process]:
    """The processes of the process group ``pgid`` now: a job's processes, whatever their parents (a helper whose
    parent ended is still the job's)."""
    members = []
    for proc in psutil.process_iter():
        try:
            if os.getpgid(proc.pid) == pgid:
                members.append(proc)
        except (ProcessLookupError, PermissionError):
            continue
    return members


def _sum_memory(processes: list[psutil.Process], proportional: bool) -> int:
    total = 0
    for proc in processes:
        try:
            total += proc.memory_full_info().pss if proportional else proc.memory_info().rss
        except (psutil.NoSuchProcess, psutil.ZombieProcess):
            continue
        except (psutil.AccessDenied, AttributeError):  # no smaps here: resident size, an upper bound
            with contextlib.suppress(psutil.Error):
                total += proc.memory_info().rss
    return total


def group_memory_over(pgid: int, limit: int) -> int | None:
    """The memory in bytes the process group ``pgid`` uses if that is over ``limit`` bytes, else ``None``: the
    resident sizes' sum first (cheap, an upper bound), and only when that is over ``limit`` the proportional set
    sizes' sum, which is the use measured (module docstring)."""
    members = group_members(pgid)
    if _sum_memory(members, proportional=False) <= limit:
        return None
    used = _sum_memory(members, proportional=True)
    return used if used > limit else None


def kill_orphans(run_dir: Path) -> list[int]:
    """Kill the process groups of job processes that outlived an earlier API (their pid files are in ``run_dir``);
    returns their pids. A pid file whose process is gone (or is another process now) is only removed."""
    killed = []
    for pid_file in sorted(run_dir.glob("*.pid")) if run_dir.is_dir() else []:
        try:
            pid_text, started, module = pid_file.read_text().split()[:3]
            pid = int(pid_text)
        except (OSError, ValueError):
            pid, started, module = 0, "", ""
        if pid > 1 and module == JOB_MODULE and _start_time(pid) == started:
            log.warning("job process %d (%s) outlived the API that started it: killed", pid, pid_file.stem)
            _signal_group(pid, signal.SIGKILL)
            killed.append(pid)
        pid_file.unlink(missing_ok=True)
    return killed


class JobProcess:
    """The process (group) running one job.

    Parameters
    ----------
    job_id : str
    settings : Settings
        Handed to the child on its stdin, without the token.
    scheduler : str, optional
        The Dask scheduler the job's tasks run on (``None``: in the job's process).
    env : dict
        Extra environment for the child (the cluster's ``COMPABS_TLS_*`` credentials).
    """

    def __init__(self, job_id: str, settings: Settings, scheduler: str | None = None,
                 env: dict[str, str] | None = None) -> None:
        self.job_id = job_id
        self.settings = settings
        self.started = time.monotonic()
        run_dir, log_dir = settings.data_dir / "run", settings.data_dir / "logs"
        run_dir.mkdir(parents=True, exist_ok=True)
        log_dir.mkdir(parents=True, exist_ok=True)
        self.log_path = log_dir / f"{job_id}.log"
        self.pid_file = run_dir / f"{job_id}.pid"
        child_env = dict(os.environ)
        child_env.update(env or {})
        child_env.pop("COMPABS_TOKEN", None)  # the job process needs no token; settings come on stdin
        child_env["PYTHONPATH"] = os.pathsep.join([PACKAGE_ROOT, *filter(None, [child_env.get("PYTHONPATH")])])
        child_env["PYTHONUNBUFFERED"] = "1"
        payload = {
            "settings": settings.model_dump(mode="json", exclude={"token", "tokens"}),
            "scheduler": scheduler,
            "parent": os.getpid(),
        }
        with open(self.log_path, "ab") as out:
            self.popen = subprocess.Popen(
                [sys.executable, "-m", JOB_MODULE, job_id],
                stdin=subprocess.PIPE, stdout=out, stderr=subprocess.STDOUT, cwd=PACKAGE_ROOT, env=child_env,
                start_new_session=True,
            )
        self.pid = self.popen.pid
        try:
            self.pid_file.write_text(f"{self.pid} {_start_time(self.pid) or '-'} {JOB_MODULE}\n")
            assert self.popen.stdin is not None
            self.popen.stdin.write(json.dumps(payload).encode())
            self.popen.stdin.close()
        except (OSError, BrokenPipeError):  # the child died at once: poll() tells, its log says why
            pass

    def elapsed(self) -> float:
        """Seconds since the job process started."""
        return time.monotonic() - self.started

    def wait(self, timeout: float) -> int | None:
        """The exit status once the process has ended (negative: the signal that killed it), else ``None`` after
        ``timeout`` seconds."""
        try:
            return self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def memory_over(self, limit: int) -> int | None:
        """The memory in bytes the job's process group uses now if that is over ``limit`` bytes, else ``None``
        (:func:`group_memory_over`); ``None`` too when it cannot be read this time (it is read again at the next
        look, and a supervisor that raised would leave the job unwatched)."""
        try:
            return group_memory_over(self.pid, limit)
        except (psutil.Error, OSError):
            return None

    def kill(self) -> int:
        """``SIGKILL`` to the whole process group at once; returns the job process's exit status."""
        _signal_group(self.pid, signal.SIGKILL)
        return self.popen.wait()

    def stop(self, grace: float) -> int:
        """Stop the whole process group: ``SIGTERM``, then ``SIGKILL`` after ``grace`` seconds. Returns the job
        process's exit status."""
        _signal_group(self.pid, signal.SIGTERM)
        code = self.wait(grace)
        _signal_group(self.pid, signal.SIGKILL)  # its helpers too, even once the leader has ended
        if code is None:
            code = self.popen.wait()
        return code

    def finish(self) -> None:
        """After the process ended: kill what is left of its group, remove the pid file."""
        _signal_group(self.pid, signal.SIGKILL)
        with contextlib.suppress(OSError):
            self.pid_file.unlink(missing_ok=True)

    def log_tail(self, lines: int = 5) -> str:
        """The last ``lines`` lines of the job's log (for the server log, not for the user)."""
        try:
            with open(self.log_path, "rb") as fh:
                fh.seek(max(0, fh.seek(0, os.SEEK_END) - 4000))
                return "\n".join(fh.read().decode(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""


def describe_exit(code: int) -> str:
    """An exit status in words: ``status 1``, ``signal SIGKILL``."""
    if code < 0:
        try:
            return f"signal {signal.Signals(-code).name}"
        except ValueError:
            return f"signal {-code}"
    return f"status {code}"
