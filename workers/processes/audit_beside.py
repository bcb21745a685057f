"""The audit in a child process, beside synthesis (``run_abstraction(session=...)``; the
:class:`~workers.job_session.JobSession` holds it until its ``finish_audit`` or ``close``).

Synthesis needs nothing the audit makes, and the audit (Theorems 4.2 and 4.7 checked on random transitions,
:func:`~pipelines.verification.audit.audit_abstraction`) is pure numpy, while synthesis is CUDD in the job's process, which holds the
GIL: a thread would not overlap it, a process does. On the 10 tanks the 2.6 s audit then costs no wall time
(the per-subsystem synthesis uses one core). The job still fails on a violation, after synthesis: a violation
never stops synthesis, it sets the job's status at the end.

The child is ``python -m workers.processes.audit_beside IN OUT PARENT_PID`` (not ``multiprocessing``, whose ``spawn``
re-runs the caller's ``__main__`` and whose ``fork`` copies a process that may hold Dask's threads). ``IN`` is a
pickle of the network (black boxes included: a ``module:function`` pickles by reference and was allowed
already), the relations, the interconnection abstraction, the transition count and the random generator, whose
state makes the child's report identical to an audit in this process. ``OUT`` holds ``("ok", report, seconds)``
or ``("error", exception)``. The child stops, and removes its folder, once ``PARENT_PID`` has died.

Progress: given a ``progress(done, total, part)`` callback, the parent hands the child the write end of a pipe
(``PROGRESS_FD``, a fourth argument); the child writes one line ``done total part`` after each part of the audit,
counted in the transitions the parts draw, and a thread of the parent relays each line to the callback. The
job's own thread is busy in synthesis meanwhile, so the relay is what makes the audit's bar move.
"""

from __future__ import annotations

import os
import pickle
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import pipelines.verification.audit as audit
from pipelines.errors import CompabsError
from workers.processes.children import start_module


class BackgroundAudit:
    """An audit running in a child process; :meth:`result` waits for it, :meth:`cancel` stops it.

    Parameters
    ----------
    network, relations, ia, count, rng
        As for :func:`~pipelines.verification.audit.audit_abstraction`; ``rng`` is copied (this process's generator is left alone).
    progress : callable, optional
        ``progress(done, total, part)``, called from a thread of this process after each part of the audit, in
        transitions drawn (``total``: all the audit draws). An exception it raises (a job's cancellation) stops
        the relay, not the child: :meth:`cancel` does.
    """

    def __init__(self, network: Any, relations: dict, ia: Any, count: int, rng: Any,
                 progress: Callable[[int, int, str], None] | None = None) -> None:
        self._dir = Path(tempfile.mkdtemp(prefix="compabs-audit-"))
        self._in, self._out, self._err = self._dir / "in.pickle", self._dir / "out.pickle", self._dir / "stderr"
        self._relay: threading.Thread | None = None
        read_fd = write_fd = -1
        try:
            with open(self._in, "wb") as fh:
                pickle.dump((network, relations, ia, int(count), rng), fh, protocol=pickle.HIGHEST_PROTOCOL)
            args = [str(self._in), str(self._out), str(os.getpid())]
            if progress is not None:
                read_fd, write_fd = os.pipe()
                args.append(str(write_fd))
            with open(self._err, "wb") as err:  # a file, not a pipe: a chatty child cannot block on a full pipe
                self._proc = start_module(
                    "workers.processes.audit_beside", *args,
                    stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err,
                    pass_fds=() if write_fd < 0 else (write_fd,),
                )
        except BaseException:
            for fd in (read_fd, write_fd):
                if fd >= 0:
                    os.close(fd)
            shutil.rmtree(self._dir, ignore_errors=True)
            raise
        # Reaped as soon as it exits, not when result() is called after synthesis: no zombie meanwhile.
        threading.Thread(target=self._proc.wait, name="audit-reaper", daemon=True).start()
        if progress is not None:
            os.close(write_fd)  # the child's copy is the only writer left: its exit ends the relay (EOF)
            pipe = os.fdopen(read_fd, "r", encoding="utf-8", errors="replace")
            self._relay = threading.Thread(target=_relay, args=(pipe, progress), name="audit-progress", daemon=True)
            self._relay.start()

    def _join_relay(self) -> None:
        """Wait for the relay to deliver the child's last lines (after the child exited, so before the caller's
        final progress event, which they must not follow)."""
        if self._relay is not None:
            # A grandchild of the audit (a black box's own process) could hold the pipe open: do not wait forever.
            self._relay.join(RELAY_JOIN)
            self._relay = None

    def result(self) -> tuple[dict[str, Any], float, float]:
        """Wait for the audit.

        Returns
        -------
        report : dict
            As :func:`~pipelines.verification.audit.audit_abstraction` returns it.
        seconds : float
            The audit's own wall time in the child.
        waited : float
            Seconds this call waited (0 when the audit finished while synthesis ran).

        Raises
        ------
        CompabsError
            What the audit raised (e.g. a black box returning NaN on an audit sample), or why the child died.
        """
        t0 = time.perf_counter()
        try:
            code = self._proc.wait()
            waited = time.perf_counter() - t0
            self._join_relay()
            if code != 0 or not self._out.exists():
                tail = self._err.read_text(errors="replace")[-2000:] if self._err.exists() else ""
                raise CompabsError(f"the audit's child process exited with status {code}: {tail.strip() or 'no message'}")
            with open(self._out, "rb") as fh:
                outcome = pickle.load(fh)
            if outcome[0] == "error":
                raise outcome[1]
            _, report, seconds = outcome
            return report, seconds, waited
        finally:
            shutil.rmtree(self._dir, ignore_errors=True)

    def cancel(self) -> None:
        """Stop the child and remove its files (idempotent)."""
        if self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait()
        self._join_relay()
        shutil.rmtree(self._dir, ignore_errors=True)


#: Seconds between the child's checks that its parent is alive.
PARENT_POLL = 0.5
#: Seconds :meth:`BackgroundAudit.result` and :meth:`~BackgroundAudit.cancel` wait for the progress relay to end.
RELAY_JOIN = 2.0


def _relay(pipe: IO[str], progress: Callable[[int, int, str], None]) -> None:
    """Parent side (a thread): hand each ``done total part`` line of the child to ``progress`` until EOF."""
    live = True
    with pipe:
        for line in pipe:  # read to EOF even once ``progress`` failed: a full pipe would block the child
            fields = line.rstrip("\n").split(" ", 2)
            if not live or len(fields) < 2:
                continue
            try:
                done, total = int(fields[0]), int(fields[1])
            except ValueError:
                continue
            try:
                progress(done, total, fields[2] if len(fields) > 2 else "")
            except Exception:  # a job's cancellation: its own thread meets it at its next event and stops the child
                live = False


def _progress_writer(fd: int, network: Any, count: int) -> Callable[[int, int, str], None]:
    """Child side: a ``progress(done, total, part)`` for :func:`~pipelines.verification.audit.audit_abstraction`
    that writes, after each part, the transitions the parts so far drew out of all the audit draws (each
    subsystem and the interconnection ``count``, the composition
    :func:`~pipelines.verification.audit.composition_transitions`) to the pipe ``fd``."""
    per_part = {"composition": audit.composition_transitions(count)}
    total = count * (len(network.unique_subsystems()) + 1) + per_part["composition"]
    pipe = os.fdopen(fd, "w", buffering=1, encoding="utf-8")
    drawn = 0

    def send(done: int, parts: int, part: str) -> None:
        nonlocal drawn
        if part:
            drawn = min(total, drawn + per_part.get(part, count))
        try:
            pipe.write(f"{drawn} {total} {' '.join(part.split()) + ' checked' if part else 'started'}\n")
        except OSError:  # the parent no longer reads (it stopped): the audit itself goes on as before
            pass

    send(0, 0, "")
    return send


def _exit_when_orphaned(parent: int, folder: Path) -> None:
    """Stop this child, and remove its folder, once ``parent`` has died (a thread of the child).

    A job's process killed outright (SIGKILL, out of memory) cannot cancel its audit; without this the child
    would finish an audit nobody reads and leave its folder behind. A dead parent's children are re-parented
    (to init or a subreaper), so a changed ``getppid()`` says the parent is gone; ``PR_SET_PDEATHSIG`` would
    say it too but fires when the *thread* that started the child exits, and a job's thread may.
    """
    import threading

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL)
        shutil.rmtree(folder, ignore_errors=True)
        os._exit(3)  # nobody waits for this child any more: no cleanup of the interpreter needed

    threading.Thread(target=watch, name="audit-parent-watch", daemon=True).start()


def main(argv: list[str]) -> int:
    """Child side: run the audit on the pickled inputs and pickle the outcome.

    ``argv`` is ``IN OUT [PARENT_PID [PROGRESS_FD]]``; with a parent pid the child stops (and removes ``IN``'s
    folder) when that process dies; with a progress fd it writes its progress there (module docstring).
    """
    src, dst, *rest = argv
    if rest:
        _exit_when_orphaned(int(rest[0]), Path(src).parent)
    with open(src, "rb") as fh:
        network, relations, ia, count, rng = pickle.load(fh)
    progress = _progress_writer(int(rest[1]), network, count) if len(rest) > 1 else None
    t0 = time.perf_counter()
    try:
        outcome: tuple = ("ok", audit.audit_abstraction(network, relations, ia, count, rng, progress=progress),
                          time.perf_counter() - t0)
    except CompabsError as exc:  # a user's error (NaN from a black box, ...): the parent raises it as it is
        outcome = ("error", exc)
    try:
        data = pickle.dumps(outcome)
    except Exception:  # an exception that does not pickle: keep its message
        data = pickle.dumps(("error", CompabsError(f"the audit failed: {outcome[1]}")))
    tmp = Path(dst + ".partial")
    tmp.write_bytes(data)
    tmp.replace(dst)  # the parent reads OUT only once it is whole
    return 0


if __name__ == "__main__":  # pragma: no cover - run as a child by BackgroundAudit
    sys.exit(main(sys.argv[1:]))
