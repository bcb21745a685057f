"""``SIGTERM`` and ``SIGHUP`` end a command like Ctrl-C does: by unwinding it.

``timeout 600 compabs run …``, a batch system's time limit or a closed terminal send ``SIGTERM`` (``SIGHUP``),
whose default action ends Python at once: no ``finally`` runs, so the embedded Dask cluster is not closed (its
``multiprocessing`` semaphores are left to the resource tracker, which warns ``resource_tracker: There appear to
be N leaked semaphore objects``), and the audit's child and the synthesis helpers are not stopped and waited for
(orphans, or zombies where nothing reaps them). Under :func:`terminate_as_interrupt` the signal raises
:class:`Terminated` in the main thread instead, which unwinds the job through every ``finally`` as
``KeyboardInterrupt`` does (it is one, so ``except Exception`` never swallows it); the command then exits with
``128 + signal``, as a shell reports a process ended by that signal.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["SIGNALS", "Terminated", "terminate_as_interrupt"]

#: The signals that end a command by unwinding it (``SIGINT`` already does, as ``KeyboardInterrupt``).
SIGNALS = (signal.SIGTERM, signal.SIGHUP)


class Terminated(KeyboardInterrupt):
    """Raised in the main thread by ``SIGTERM`` or ``SIGHUP`` under :func:`terminate_as_interrupt`."""

    def __init__(self, signum: int) -> None:
        self.signum = int(signum)
        self.name = signal.Signals(self.signum).name
        super().__init__(f"stopped by {self.name}")

    @property
    def status(self) -> int:
        """The exit status a shell gives a process ended by this signal (``128 + signal``: 143 for SIGTERM)."""
        return 128 + self.signum


@contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Within the block, :data:`SIGNALS` raise :class:`Terminated` in the main thread; the handlers before are
    restored after it. A second signal while the first unwinds is ignored, so the cleanup is not cut short (a
    ``timeout -k`` still ends it with ``SIGKILL``). Outside the main thread (a caller's thread), nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.getsignal(s) for s in SIGNALS}

    def stop(signum: int, frame: object) -> None:
        for s in SIGNALS:
            signal.signal(s, signal.SIG_IGN)
        raise Terminated(signum)

    for s in SIGNALS:
        signal.signal(s, stop)
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
